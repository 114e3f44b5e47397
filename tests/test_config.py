from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError

from gpnerf_core.config.compose import config_dir
from gpnerf_core.config.compose import register_schema
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.kinds import KINDS, section

EXPERIMENTS = sorted(
    str(p.relative_to(Path(config_dir()) / "experiment").with_suffix(""))
    for p in (Path(config_dir()) / "experiment").rglob("*.yaml")
)


@pytest.fixture(scope="module")
def registry():
    registry = get_registry()
    register_schema()
    return registry


def compose_with(overrides):
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def test_default_config_composes_with_cpu_scale(registry):
    cfg = compose_with(["+head=unet", "+loss=dgs"])
    assert cfg.head.name == "unet" and cfg.loss.name == "dgs"
    assert cfg.model.feature_extractor.name == "resunet_fpn" and cfg.model.field_aggregator.width == 32
    assert cfg.model.coarse_samples == 24
    assert "feature_extractor" not in cfg and "field_aggregator" not in cfg  # the family's parts sit under model


def test_paper_scale_restores_paper_sizes(registry):
    cfg = compose_with(["scale=paper", "+head=unet", "+loss=dgs"])
    assert list(cfg.model.feature_extractor.widths) == [64, 64, 128, 256]
    assert cfg.model.feature_extractor.fpn_channels * 4 == 512
    assert cfg.model.field_aggregator.width == 64 and cfg.model.field_aggregator.num_blocks == 8
    assert (cfg.model.coarse_samples, cfg.model.fine_samples, cfg.model.num_source_views) == (48, 16, 10)
    assert cfg.train.rays == 512 and cfg.model.lr.transformer == 1e-5


@pytest.mark.parametrize("kind", list(KINDS))
def test_every_registered_option_composes(registry, kind):
    for name in registry.names(kind):
        add_on = KINDS[kind].add_on
        prefix = "+" if add_on else ""
        extra = [] if kind in ("head", "loss") else ["+head=unet", "+loss=dgs"]
        for scale in ("cpu", "paper"):  # each component's size preset is its own, so any option composes with both
            cfg = compose_with([f"{prefix}{KINDS[kind].group}={name}", *extra, f"scale={scale}"])
            assert section(cfg, kind).name == name


def test_each_family_brings_the_parts_it_declares(registry):
    """``model=<name>`` chooses the family's own parts (its config's ``part`` fields) and no other part kind."""
    from gpnerf_core.registry.declarations import declared_parts

    for name in registry.names("model"):
        cfg = compose_with([f"model={name}"])
        declared = declared_parts(registry.get("model", name).spec.config)
        assert {kind: cfg.model[kind].name for kind in declared} == declared
        assert all(kind in declared or kind not in cfg.model for kind in ("feature_extractor", "field_aggregator",
                                                                           "ray_aggregator"))


def test_a_part_is_chosen_and_sized_under_the_model(registry):
    cfg = compose_with(["model=mvsnerf", "model/feature_extractor=resunet_fpn", "model.feature_extractor.fpn_channels=8"])
    assert cfg.model.feature_extractor.name == "resunet_fpn" and cfg.model.feature_extractor.fpn_channels == 8
    assert list(cfg.model.feature_extractor.widths) == [32, 32, 64, 96]  # scale=cpu's resunet_fpn, under any family
    with pytest.raises(ConfigCompositionException):  # a part the family does not build has no place under it
        compose_with(["model=semantic_nerf", "model/feature_extractor=resunet_fpn"])


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(registry, experiment):
    cfg = compose_with([f"+experiment={experiment}"])
    own_terms = experiment.startswith("baselines/mask_rcnn")  # a 2D detector trains on its own terms: no loss set
    assert (cfg.loss is None) == own_terms
    if own_terms:
        assert cfg.model.name == "mask_rcnn" and cfg.get("head") is None
        backbones = {"baselines/mask_rcnn_swin_t": "swin_t", "baselines/mask_rcnn_torchvision": "resnet50"}
        assert cfg.model.backbone == backbones.get(experiment, "resnet34")
        return
    label_rendering_families = ("baselines/semantic_ray", "baselines/neuray", "baselines/mvsnerf",
                                "baselines/semantic_nerf", "baselines/semantic_nerf_grid")
    assert (cfg.get("head") is None) == (experiment in ("baselines/gnt", "baselines/dm_nerf", "baselines/mvsplat",
                                                        "baselines/semantic_3dgs",
                                                        *label_rendering_families))
    if experiment in label_rendering_families:  # the compared methods: their own family, scored by label rendering
        family = experiment.split("/")[1].removesuffix("_grid")  # semantic_nerf_grid: the family's grid option
        assert cfg.model.name == family and cfg.loss.name == "ce"
        assert cfg.model.get("field", "mlp") == ("grid" if experiment.endswith("_grid") else "mlp")
    if experiment == "baselines/dm_nerf":  # per-scene instances: its own object field and loss set
        assert cfg.model.name == cfg.loss.name == "dm_nerf"
    if experiment.endswith("_unet") and experiment != "baselines/gpnerf_unet":  # another family, GP-NeRF's decoding
        assert cfg.model.name == experiment.split("/")[1].removesuffix("_unet") and cfg.head.name == "unet"


def test_baselines_share_the_backbone_and_differ_in_the_semantic_path(registry):
    from gpnerf_core.model.build import build_model

    models = {}
    for name in ("gnt", "label_rendering", "gpnerf_unet"):
        cfg = compose_with([f"+experiment=baselines/{name}"])
        models[name] = (cfg, build_model(cfg, num_classes=5))
    gnt_cfg, gnt = models["gnt"]
    assert gnt_cfg.loss.name == "rgb" and gnt.head is None and gnt.semantic is None and not gnt.has_semantics
    assert models["label_rendering"][0].head.name == "per_pixel" and models["label_rendering"][0].loss.name == "ce"
    assert models["gpnerf_unet"][0].head.name == "unet" and models["gpnerf_unet"][0].loss.name == "dgs"
    trunk = [sum(p.numel() for p in model.field.parameters()) for _, model in models.values()]
    assert len(set(trunk)) == 1  # the same field aggregator in all three


def test_table4_switches(registry):
    expected = {
        "table4_id1": ("ce", False, None),
        "table4_id2": ("ce", True, None),
        "table4_id3": ("sd", True, False),
        "table4_id4": ("sd", True, True),
        "table4_id5": ("dgs", True, True),
    }
    for experiment, (loss, joint, block) in expected.items():
        cfg = compose_with([f"+experiment={experiment}"])
        assert cfg.loss.name == loss and cfg.model.semantic_field.joint_attention is joint
        if block is not None:
            assert cfg.loss.teacher_stop_grad is block and cfg.loss.sd_weight > 0


def test_misspelled_key_fails(registry):
    with pytest.raises((ConfigCompositionException, ConfigKeyError)):
        compose_with(["+head=unet", "+loss=dgs", "train.step=3"])


def test_unknown_head_lists_known_options(registry):
    with pytest.raises(ConfigCompositionException) as info:
        compose_with(["+head=nope", "+loss=dgs"])
    assert "unet" in str(info.value.__cause__ or info.value) or "unet" in str(info.value)


@pytest.mark.parametrize("dataset", ["scannet", "replica", "replica_instance"])
def test_real_datasets_compose_with_experiments(registry, dataset):
    cfg = compose_with([f"dataset={dataset}", "dataset.root=/data", "+experiment=table4_id5"])
    assert cfg.dataset.name == dataset and cfg.loss.name == "dgs"


def test_a_hydra_glob_sweep_finds_the_five_table4_rows():
    """``run -m '+experiment=glob(table4_*)'``: Hydra's glob lists one config group level, so the rows live there."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.types import Glob

    register_schema()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        options = GlobalHydra.instance().config_loader().get_group_options("experiment")
    assert Glob(include=["table4_*"]).filter(options) == [f"table4_id{i}" for i in range(1, 6)]


def test_the_primary_config_picks_a_size_preset_for_every_part_kind_and_the_family():
    """``conf/config.yaml`` lists one optional ``scale`` entry per part kind (``model.<kind>``) and one for the family:
    a part kind added to ``registry/kinds.py`` needs its entry there."""
    import yaml

    from gpnerf_core.registry.kinds import PART_KINDS

    defaults = yaml.safe_load((Path(config_dir()) / "config.yaml").read_text())["defaults"]
    entries = [e for e in defaults if not isinstance(e, str)]
    presets = {key: value for entry in entries for key, value in entry.items() if key.startswith("optional scale@")}
    assert presets == {**{f"optional scale@model.{kind}": f"${{scale}}/{kind}/${{model/{kind}}}" for kind in PART_KINDS},
                       "optional scale@_global_": "${scale}/${model}"}


@pytest.mark.parametrize("experiment", ["baselines/mvsplat", "baselines/mvsplat_unet"])
def test_mvsplat_clips_gradients_at_the_official_0_5(registry, experiment):
    """Issue 55: MVSplat's ``gradient_clip_val`` 0.5 (config/main.yaml), on the CPU scale and the experiments."""
    assert compose_with([f"+experiment={experiment}"]).train.grad_clip == 0.5
    assert compose_with(["model=mvsplat", "+loss=image"]).train.grad_clip == 0.5
