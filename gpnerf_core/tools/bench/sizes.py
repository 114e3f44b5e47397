"""Benchmark presets: the model and data sizes ``bench size=<name>`` measures, and the GNT-only anchor of each.

Every preset trains on one generated embedded scene at the preset's image size (16 frames: enough training frames for
10 source views); rendering is timed on one of its held-out views.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from gpnerf_core.errors import ConfigError

DATA = [
    "dataset.num_train_scenes=1",
    "dataset.num_unseen_scenes=1",
    "dataset.frames_per_scene=16",
    "eval.render_stride=2",  # both variants render the same rays: the semantic map's grid
]


@dataclass(frozen=True)
class Size:
    """A benchmark size.

    Attributes:
        name: ``demo``, ``small``, ``paper``.
        description: one line.
        common: overrides shared by both variants (model sizes, image size, rays, samples).
        semantic: what makes the GP-NeRF variant (head, loss set and its weights).
    """

    name: str
    description: str
    common: tuple[str, ...]
    semantic: tuple[str, ...]


GNT_ONLY = ("+loss=rgb", "model.semantic_field.enabled=false", "model.feature_extractor.semantic=false")
"""The anchor: the same backbone, rays and samples with no FPN, no semantic field, no head, colour loss only."""

PAPER_LOSS = ("+loss=dgs", "loss.rgb_weight=0.75", "loss.ce_weight=1.5", "loss.sd_weight=0.25", "loss.dgs_weight=0.25")

SIZES: dict[str, Size] = {
    size.name: size
    for size in (
        Size(
            "demo",
            "the main job's model (scale=cpu): 96x128 images, 4 views, 24+8 samples, 256 rays, 4 blocks of width 32",
            ("scale=cpu", "dataset.height=96", "dataset.width=128", "train.rays=256", *DATA),
            ("+head=unet", "+loss=dgs"),
        ),
        Size(
            "small",
            "the paper's model at 96x128 images: 10 views, 48+16 samples, 128 rays, 8 blocks of width 64",
            ("scale=paper", "dataset.height=96", "dataset.width=128", "train.rays=128", *DATA),
            ("+head=unet", "head.decoder=semantic_fpn", *PAPER_LOSS),
        ),
        Size(
            "paper",
            "the paper's setting: 240x320 images, 10 views, 48+16 samples, 512 rays, 8 blocks of width 64, Semantic-FPN",
            ("scale=paper", "dataset.height=240", "dataset.width=320", "train.rays=512", *DATA),
            ("+head=unet", "head.decoder=semantic_fpn", *PAPER_LOSS),
        ),
    )
}


def get_size(name: str) -> Size:
    if name not in SIZES:
        raise ConfigError(f"bench size={name!r} is unknown; known sizes: {', '.join(SIZES)}")
    return SIZES[name]


VARIANTS = ("gpnerf", "gnt_only")
"""What ``bench`` measures at each size: GP-NeRF, and its GNT-only anchor (``GNT_ONLY``)."""


def _experiment_text(family: str) -> str:
    """The text of ``conf/experiment/baselines/<family>.yaml`` and of the baseline experiments its defaults include
    (``- /experiment/baselines/<other>``: a variant of another baseline's family)."""
    import re

    from gpnerf_core.config.compose import config_dir

    text = (Path(config_dir()) / "experiment" / "baselines" / f"{family}.yaml").read_text()
    included = re.findall(r"^\s*-\s*/experiment/baselines/(\w+)\s*$", text, flags=re.MULTILINE)
    return "\n".join([text, *(_experiment_text(other) for other in included)])


def baseline_families() -> list[str]:
    """The compared methods' experiments (``conf/experiment/baselines/<name>.yaml``) that select a model family other
    than GP-NeRF's, themselves or through a baseline experiment they include (the families ``bench families=...`` may
    measure)."""
    from gpnerf_core.config.compose import config_dir

    folder = Path(config_dir()) / "experiment" / "baselines"
    return sorted(p.stem for p in folder.glob("*.yaml") if "override /model:" in _experiment_text(p.stem))


def registered_families() -> list[str]:
    """Every model family a plugin registers (third parties' too), the default one aside (``conf/config.yaml``'s
    ``model``: GP-NeRF's, which the ``gpnerf`` and ``gnt_only`` variants measure)."""
    from gpnerf_core.config.overrides import default_choice
    from gpnerf_core.registry.components import get_registry

    default = default_choice("model")
    return [name for name in get_registry().names("model") if name != default]


def project_experiments() -> list[str]:
    """The project's own experiments (``conf/experiment/<name>.yaml``: ``instance``, ``table4_id1``...): GP-NeRF with
    another head or loss set, measured beside GP-NeRF as ``+experiment=<name>`` on the size's images, views and rays."""
    from gpnerf_core.config.compose import config_dir

    return sorted(p.stem for p in (Path(config_dir()) / "experiment").glob("*.yaml"))


def checked_families(value: str) -> list[str]:
    """``bench families=<a,b>``: each a compared method's experiment (``baselines/<name>``), a registered model family
    (a third party's, measured as ``model=<name>``) or one of the project's own experiments (``instance``), refused in
    one line when one is none of them."""
    names = [n.strip() for n in value.split(",") if n.strip()]
    known = sorted({*baseline_families(), *registered_families(), *project_experiments()})
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ConfigError(f"bench families={value!r}: expected some of {', '.join(known)} (comma-separated: the "
                          "baseline experiments, the registered model families and the project's experiments)")
    return names


def check_family_overrides(overrides: list[str]) -> None:
    """The overrides keep GP-NeRF's family: ``bench``'s own variants are GP-NeRF and its GNT-only anchor, whose
    overrides (``GNT_ONLY``, a size's head and loss) are options of that family only; another family is measured
    beside them with ``families=<name>``.

    Raises:
        ConfigError: ``model=<another family>`` or an experiment that selects one, naming it and ``families=``.
    """
    from gpnerf_core.config.compose import compose
    from gpnerf_core.config.overrides import default_choice, is_search_path, override_key

    default = default_choice("model")
    for override in overrides:
        key, _, value = override.lstrip("+~").partition("=")
        if override_key(override) not in ("model", "experiment") or not value:
            continue
        if key == "experiment":
            try:
                value = str(compose([*(o for o in overrides if is_search_path(o)), override]).model.name)
            except Exception:  # noqa: BLE001 - composing the variants names what is wrong
                continue
        if value != default:
            name = override.partition("=")[2].rpartition("/")[2] if key == "experiment" else value
            measured = name if name in {*baseline_families(), *registered_families()} else value
            raise ConfigError(f"bench {override}: bench measures GP-NeRF (model={default}) and its GNT-only anchor, "
                              f"whose overrides are options of that family only (not of model {value!r}); measure {value} "
                              f"beside them with families={measured} (drop {override})")


def variant_overrides(size: Size, variant: str, overrides: list[str]) -> list[str]:
    """The overrides of ``variant`` at ``size``, the user's last (they win): ``gpnerf``, ``gnt_only``, a baseline
    family (its ``+experiment=baselines/<variant>`` on the size's common overrides: the same images, views and rays),
    a registered family with a plugin's preset or one of the project's experiments (``+experiment=<variant>``,
    ``plugin_experiment``, ``project_experiments``), or another registered
    family (``model=<variant>`` and ``family_defaults``' loss set on them). A per-scene family is evaluated on its
    scene's held-out frames (``eval.splits=[train]``). The user's overrides a family does not take are left out for it
    (``dropped_overrides`` names them)."""
    if variant in VARIANTS:
        extra = size.semantic if variant == "gpnerf" else GNT_ONLY
        return [*size.common, *extra, *overrides]
    common = family_common(size, variant)
    return [*common, *_accepted(common, tuple(overrides))[0]]


def dropped_overrides(size: Size, variant: str, overrides: list[str]) -> list[str]:
    """The user's overrides ``variant`` does not take at ``size`` (none for GP-NeRF's variants): options of parts it
    does not build, ``model.<key>`` it has no field for, and source views for a per-scene family."""
    if variant in VARIANTS:
        return []
    return _accepted(family_common(size, variant), tuple(overrides))[1]


def family_common(size: Size, variant: str) -> tuple[str, ...]:
    """A family variant's overrides before the user's (the size's, its preset or model, its loss set and splits)."""
    if variant in baseline_families():  # the size's scale sizes the family as it sizes its own (scale/<scale>/<model>)
        common = (*size.common, f"+experiment=baselines/{variant}")
    elif plugin_experiment(variant) or variant in project_experiments():
        common = (*size.common, f"+experiment={variant}")
    else:
        base = (*size.common, f"model={variant}")
        common = (*base, f"+loss={family_loss(base, variant)}", *loss_options(base))
    return (*common, "eval.splits=[train]") if family_per_scene(common) else common


def plugin_experiment(family: str) -> bool:
    """A plugin ships ``experiment/<family>.yaml`` (its preset for its family, ``+experiment=<family>``)."""
    from gpnerf_core.config.presets import config_files, plugin_search_paths

    return any(f"experiment/{family}.yaml" in config_files(path) for _, path in plugin_search_paths())


def _accepted(common: tuple[str, ...], overrides: tuple[str, ...]) -> tuple[list[str], list[str]]:
    """``(kept, dropped)``: ``overrides`` split by whether the family ``common`` composes takes them."""
    from gpnerf_core.config.overrides import override_key

    kept = own_parts(common, list(overrides))
    dropped = [o for o in overrides if o not in kept]
    if not any(override_key(o).startswith("model.") for o in kept):
        return kept, dropped
    # a key the family has no field for would be refused by Hydra; source views, by a per-scene family's check
    fields = family_fields(common)
    per_scene = family_per_scene(common)

    def takes(override: str) -> bool:
        key = override_key(override)
        if not key.startswith("model.") or override.startswith("+"):
            return True
        name = key.split(".")[1]
        return name in fields and not (per_scene and name == "num_source_views")

    return [o for o in kept if takes(o)], [*dropped, *(o for o in kept if not takes(o))]


def own_parts(common: tuple[str, ...], overrides: list[str]) -> list[str]:
    """``overrides`` without those of parts the family ``common`` composes does not build (``model.<kind>.*``,
    ``model/<kind>=``): options given for GP-NeRF's parts apply to another family where it has those parts."""
    from gpnerf_core.config.overrides import override_key
    from gpnerf_core.registry.kinds import GROUPS, PART_KINDS

    def part(override: str) -> str | None:
        key = override_key(override)
        kind = GROUPS.get(key) or (key.split(".")[1] if key.startswith("model.") and "." in key[6:] else None)
        return kind if kind in PART_KINDS else None

    if not any(part(o) for o in overrides):
        return list(overrides)
    built = family_parts(common)
    return [o for o in overrides if part(o) is None or part(o) in built]


@functools.cache
def family_fields(common: tuple[str, ...]) -> frozenset[str]:
    """The top-level keys of the model section ``common`` composes."""
    from gpnerf_core.config.compose import compose

    return frozenset(str(key) for key in compose(list(common)).model)


@functools.cache
def family_parts(common: tuple[str, ...]) -> frozenset[str]:
    """The part kinds under the model ``common`` composes."""
    from gpnerf_core.config.compose import compose
    from gpnerf_core.registry.kinds import PART_KINDS

    model = compose(list(common)).model
    return frozenset(kind for kind in PART_KINDS if kind in model)


@functools.cache
def family_per_scene(common: tuple[str, ...]) -> bool:
    """The family ``common`` composes is per-scene: its config's ``num_source_views`` defaults to 0 (the rule the
    config check holds a family to); False when it does not compose (the variant's compose names why)."""
    import dataclasses

    from gpnerf_core.config.compose import compose
    from gpnerf_core.registry.components import get_registry

    try:
        name = str(compose(list(common)).model.name)
    except ConfigError:
        return False
    registered = get_registry().components["model"].get(name)
    fields = {f.name: f for f in dataclasses.fields(registered.spec.config)} if registered else {}
    views = fields.get("num_source_views")
    return views is not None and views.default == 0


@functools.cache
def family_built(common: tuple[str, ...]) -> tuple[str | None, bool]:
    """``(predicts, whole_images)`` of the model ``common`` composes, as built: ``classes``, ``instances`` or None
    (colour only), and whether it trains on whole images; ``("classes", False)`` when it is refused (the variant's
    compose names why)."""
    from gpnerf_core.config.compose import compose
    from gpnerf_core.interfaces.head import Predicts
    from gpnerf_core.interfaces.model import TrainingBatch
    from gpnerf_core.model.build import build_components

    try:
        model = build_components(compose(list(common))).model
    except ConfigError:
        return "classes", False
    output = model.semantic_output
    return (None if output is None else Predicts(output.predicts).value,
            model.capabilities.trains_on is TrainingBatch.IMAGES)


def family_loss(common: tuple[str, ...], family: str) -> str:
    """The loss set a registered family without a preset is measured with, by what it predicts and trains on: on
    whole images ``image`` (its cross-entropy only for classes, ``loss_options``); on rays ``ce`` for classes,
    ``instance`` for instance slots, ``rgb`` for colour only. A family refused as composed gets ``ce`` (the compose
    of the variant names why)."""
    predicts, whole_images = family_built(common)
    if whole_images:
        return "image"
    return {"classes": "ce", "instances": "instance"}.get(predicts or "", "rgb")


def loss_options(common: tuple[str, ...]) -> tuple[str, ...]:
    """Options of ``family_loss``'s set: the image set's cross-entropy off for a family without class scores."""
    predicts, whole_images = family_built(common)
    if whole_images and predicts != "classes":
        return ("loss.ce_weight=0",)
    return ()
