"""Opening a trained model, the one way every command and tool does it (``open_trained``; detectron2's
``default_setup`` and nerfstudio's ``eval_setup``): the checkpoint's settings restored into the config, the config
validated once, the process set up once, the model built with the checkpoint's classes and its weights loaded.

``eval``, ``render``, ``view``, ``export``, ``label`` and ``finetune`` get their config from Hydra, composed from the
checkpoint's overrides and the command's (``launching.launch_from_checkpoint``, whose read of the checkpoint reaches the
job); ``stress`` and the viewer's timing compose the same overrides without Hydra. Both end here, and here a
per-scene model pointed at data without its scene is refused (``engine.fitted_data``; ``finetune`` opts out).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from omegaconf import DictConfig, OmegaConf

from gpnerf_core.config.overrides import is_search_path, merge_overrides, override_key
from gpnerf_core.data.dataset import FittedScenes
from gpnerf_core.engine.fitted_data import check_fitted_data, fitted_scenes
from gpnerf_core.engine.runs import task_overrides
from gpnerf_core.engine.setup import compose_overrides, start
from gpnerf_core.engine.validation import check_data
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.build import Components, build_components
from gpnerf_core.model.checkpoint import format_differences, model_differences
from gpnerf_core.model.trained import TrainedModel, load_trained, restore_model_settings
from gpnerf_core.model.weights import load_weights


@dataclass(frozen=True)
class OpenedModel:
    """A trained model opened for a command (``open_trained``).

    Attributes:
        trained: the checkpoint (``model.trained.load_trained``): its path, step, config and overrides.
        cfg: the command's config, the checkpoint's model settings restored where the command did not set them,
            validated.
        components: built from ``cfg``, with the checkpoint's classes where the dataset has none; the model holds the
            chosen weights and sits on ``device``.
        device: where the model is (the job's device, or the one ``cfg.device`` resolves to).
        weights: which weights it holds: ``average`` (the run's weight average) or ``trained`` (``eval.weights``).
        notes: one line per thing said about the opening: config keys restored from the checkpoint, options it had that
            this version lacks, classes taken from it.
        reinitialised: tensors that kept their fresh initialisation for another class count (``new_classes``), and
            checkpoint_classes the checkpoint's class count then (None when none did).
        fitted: a per-scene model's scenes (``chosen_scene`` takes only those and defaults to its own); None for a
            generalizable one.
    """

    trained: TrainedModel
    cfg: DictConfig
    components: Components
    device: torch.device
    weights: str
    notes: list[str]
    reinitialised: list[str]
    checkpoint_classes: int | None
    fitted: FittedScenes | None


RENDERING_COMMANDS = ("render", "view", "export", "label")
"""Commands that render poses without a real image: a 2D model (``Capabilities.segments_image``) is refused by them."""


def open_trained(
    trained: TrainedModel | None,
    overrides: Sequence[str] | None = None,
    *,
    cfg: DictConfig | None = None,
    command: str,
    validated: bool = False,
    device: torch.device | None = None,
    weights: str | None = None,
    new_classes: bool = False,
    source: str = "checkpoint {path}",
    check_scenes: bool = False,
    other_data: bool = False,
) -> OpenedModel:
    """Open a trained model for ``command``: config, validation, process set-up, build, weights. Nothing is written.

    Args:
        trained: the checkpoint, read (``load_trained``); None in a Hydra job the launcher's read did not reach (a job
            pickled into another process): ``cfg.checkpoint`` is read here.
        overrides: the command's overrides as typed; the checkpoint's own are told apart. Without ``cfg`` they are
            composed after the checkpoint's (``merge_overrides``; the command's win), as Hydra composes a job's. None:
            this Hydra job's (``task_overrides``; none outside a job).
        cfg: Hydra's config of this job (composed from the checkpoint's overrides and the command's); None: composed
            here. It is changed in place: the checkpoint's model settings restored (``restore_trained_settings``).
        command: the command's name, for the errors.
        validated: ``cfg`` was validated before Hydra (``launching.Handover.validated``): not again.
        device: where the model goes (a job's ``dist.device``); None: the device ``cfg.device`` resolves to.
        weights: ``average`` or ``trained``; None: ``cfg.eval.weights``.
        new_classes: a tensor sized by another class count keeps its initialisation (``finetune`` on another dataset);
            any other shape that differs is blamed on the model keys that differ from the checkpoint's.
        source: how the errors of the weights name the checkpoint (``{path}``: its path).
        check_scenes: ``eval``'s checks: a per-scene model is scored on its own scene only, and the evaluated splits'
            data is checked (``check_data``).
        other_data: the command fits the model on other data (``finetune``): a per-scene model is not refused for a
            dataset without its scene (``fitted_data.check_fitted_data``, which every other command passes).

    Raises:
        ConfigError: no ``checkpoint=`` in a job, ``model=`` of another family than the checkpoint's, a value the
            schema refuses, a model config whose tensors do not fit the checkpoint's (naming the keys that differ), a
            per-scene model pointed at data without the scene it was fitted on.
        DataError: the checkpoint unreadable or damaged, its weights missing, extra or not finite.
    """
    if cfg is None:
        if trained is None:
            raise TypeError("open_trained: give the checkpoint read (load_trained), or a Hydra job's cfg")
        own = list(overrides or ())
        check_family_choice(trained, own, command)
        cfg = compose_overrides(merge_overrides(trained.overrides, own))
    else:
        trained = _checkpoint_of(cfg, trained, command)
        own = list(task_overrides() if overrides is None else overrides)
    notes = restore_trained_settings(cfg, trained, own, command)
    resolved = start(cfg, validated=validated)
    components = build_components(cfg, classes=trained.classes)
    if components.model.capabilities.segments_image and command in RENDERING_COMMANDS:
        raise ConfigError(f"{command} renders novel views, and model={cfg.model.name} is a 2D model that segments a "
                          "real image (Capabilities.segments_image); score its held-out frames with eval")
    fitted = fitted_scenes(cfg, components, trained)
    if not other_data:
        asked = OmegaConf.select(cfg, f"{command}.scene", default="")
        check_fitted_data(cfg, components, trained, fitted, command, str(asked or ""))
    if components.classes.from_checkpoint:
        notes.append(components.classes.note(str(cfg.dataset.name)))
    chosen, which = trained.weights(str(cfg.eval.weights) if weights is None else weights)
    old = trained.classes.num_classes if trained.classes is not None else None
    current = OmegaConf.to_yaml(cfg, resolve=True)
    reinitialised = load_weights(
        components.model, chosen, source.format(path=trained.path),
        new_classes=(old, components.classes.num_classes) if new_classes and old is not None else None,
        explain=lambda: format_differences(model_differences(trained.config_yaml, current, trained.model_sections))
        or "no key (a different plugin version?)",
    )
    checkpoint_classes = int(chosen[reinitialised[0]].shape[0]) if reinitialised else None
    if check_scenes:
        if fitted is not None:
            _check_evaluated_scenes(cfg, components, fitted)
        check_data(cfg, components, training=False)
    where = device or resolved
    components.model.to(where)
    return OpenedModel(trained, cfg, components, where, which, notes, reinitialised, checkpoint_classes, fitted)


def check_family_choice(trained: TrainedModel, overrides: Sequence[str], command: str) -> None:
    """The command's own ``model=`` and ``+experiment=`` choose the checkpoint's family, checked before the rest is
    composed: an experiment of another family would otherwise be refused over a loss or key it brings (its ``+loss``
    clashing with the checkpoint's), never over the family.

    Raises:
        ConfigError: ``model=`` or an experiment's model is another family than the checkpoint's.
    """
    family = trained.family
    own = [o for o in overrides if o not in trained.overrides]
    for override in own:
        key, _, value = override.lstrip("+~").partition("=")
        if key == "model" and value and value != family:
            raise ConfigError(f"model={value}: checkpoint {trained.path} holds a trained model {family!r}; {command} "
                              f"takes its model family from the checkpoint: drop model=...")
        if key == "experiment" and value:
            chosen = _experiment_family(override, [o for o in own if is_search_path(o)])
            if chosen is not None and chosen != family:
                raise ConfigError(
                    f"{override}: the experiment trains model {chosen!r}, but checkpoint {trained.path} is a "
                    f"{family} model; {command} takes its model family from the checkpoint: drop {override}, or "
                    f"train a {chosen} model first (run {override})")


def _experiment_family(override: str, search_path: list[str]) -> str | None:
    """The model family the experiment ``override`` selects; None when it does not compose on its own (the full
    composition then says why)."""
    try:
        return str(compose_overrides([*search_path, override]).model.name)
    except Exception:  # noqa: BLE001 - any failure is reported by the composition that follows
        return None


def restore_trained_settings(cfg: DictConfig, trained: TrainedModel, overrides: Sequence[str],
                             command: str) -> list[str]:
    """Give ``cfg`` the checkpoint's model settings wherever the command did not set them (``restore_model_settings``);
    the notes on restored keys.

    Args:
        overrides: the overrides ``cfg`` was composed from, or the command's alone: those the checkpoint holds too are
            not the command's.

    Raises:
        ConfigError: the command chose ``model=`` another family than the checkpoint's (it takes its family from it).
    """
    typed = [override_key(o) for o in overrides if o not in trained.overrides]
    family = trained.family
    if "model" in typed and str(cfg.model.name) != family:
        raise ConfigError(f"model={cfg.model.name}: checkpoint {trained.path} holds a trained model {family!r}; "
                          f"{command} takes its model family from the checkpoint: drop model=...")
    return restore_model_settings(cfg, trained, typed)


def _checkpoint_of(cfg: DictConfig, trained: TrainedModel | None, command: str) -> TrainedModel:
    """The checkpoint ``cfg.checkpoint`` names: ``trained`` when that is it (the launcher's read), else read now."""
    if not cfg.checkpoint:
        raise ConfigError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    if trained is not None and Path(str(cfg.checkpoint)).absolute() == trained.path.absolute():
        return trained
    return load_trained(str(cfg.checkpoint))


def _check_evaluated_scenes(cfg: DictConfig, components: Any, fitted: FittedScenes) -> None:
    """A per-scene model is scored on its own scene: any other scene of the evaluated splits is refused."""
    for split in cfg.eval.splits:
        foreign = [name for name in components.dataset.scenes(str(split)) if name not in fitted.scenes]
        if foreign:
            key = "dataset.scenes" if str(split) == "train" else "eval.splits"
            raise ConfigError(f"eval.splits has {split!r} with scene {foreign[0]!r}, but {fitted.why}; set "
                              f"dataset.scenes=[{','.join(fitted.scenes)}] and eval.splits=[train] ({key} names "
                              f"another scene)")
