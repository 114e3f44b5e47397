"""The data a per-scene model was fitted on, and the one refusal of a command pointed at other data.

A per-scene family (``Capabilities.generalizable`` False) holds one scene in
its parameters, so it can show, score, export or label that scene alone. ``eval``, ``render``, ``export``, ``label``,
``view``, ``stress`` and the viewer's timing open a model through ``engine.opening``, which asks here before any
frame is read: a dataset that does not hold the fitted scene (another dataset, another capture under
``dataset.root``, ``dataset.scenes`` naming another scene) is refused in one line naming the scene the model was
fitted on and the one asked, instead of failing later over a missing folder or options inherited from the checkpoint
(a ``dataset.labels_from`` of the fitted capture). ``finetune`` opts out: it fits a model on new scenes by design.
"""

from __future__ import annotations

from typing import Any

import yaml
from omegaconf import DictConfig

from gpnerf_core.data.dataset import FittedScenes
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.model.trained import TrainedModel

SHOWN = 3
"""Scenes of the asked dataset named in a refusal."""


def fitted_scenes(cfg: DictConfig, components: Any, trained: TrainedModel) -> FittedScenes | None:
    """The scenes a per-scene model (``Capabilities.generalizable`` False) was fitted on, from its checkpoint; None for
    a generalizable model, or a checkpoint that names none."""
    if components.model.capabilities.generalizable or not trained.scenes:
        return None
    scenes = trained.scenes
    shown = f"scene {scenes[0]!r}" if len(scenes) == 1 else f"scenes {', '.join(map(repr, scenes))}"
    return FittedScenes(scenes, f"model {cfg.model.name!r} was fitted on {shown} alone (checkpoint {trained.path}): a "
                                "per-scene model renders only its scene")


def fitted_dataset_config(trained: TrainedModel) -> dict[str, Any]:
    """The ``dataset`` section of a model's stored config ({} when it has none)."""
    config = yaml.safe_load(trained.config_yaml) or {}
    dataset = config.get("dataset") if isinstance(config, dict) else None
    return dataset if isinstance(dataset, dict) else {}


def fitted_dataset(trained: TrainedModel) -> str:
    """The dataset a model was trained on (its stored config's ``dataset.name``; "" when it names none)."""
    return str(fitted_dataset_config(trained).get("name") or "")


def changed_content_key(cfg: DictConfig, trained: TrainedModel) -> tuple[str, Any, Any] | None:
    """``(key, fitted value, asked value)`` of the first of the dataset's ``content_keys`` (``DatasetConfig``) whose
    value differs from the one the model was fitted with; None when all agree (or the checkpoint stores none)."""
    from gpnerf_core.registry.components import get_registry

    stored = fitted_dataset_config(trained)
    spec = get_registry().get("dataset", str(cfg.dataset.name)).spec
    for key in getattr(spec.config, "content_keys", ()):
        if key in stored and key in cfg.dataset and stored[key] != cfg.dataset[key]:
            return key, stored[key], cfg.dataset[key]
    return None


def check_fitted_data(cfg: DictConfig, components: Any, trained: TrainedModel, fitted: FittedScenes | None,
                      command: str, asked: str = "") -> None:
    """Refuse, in one line, a per-scene model pointed at data that does not hold the scene it was fitted on.

    Args:
        fitted: ``fitted_scenes``'s answer (None: a generalizable model; nothing to check).
        command: the command's name, for the message.
        asked: the scene the command was asked for (``render.scene``, ...; "" when none was named).

    Raises:
        ConfigError: ``dataset=`` another dataset than the fitted one, or the dataset's training scenes (its root's
            folders, ``dataset.scenes``) lack a fitted scene; the message names the fitted scene, the asked one and
            the fix.
    """
    if fitted is None:
        return
    own = fitted_dataset(trained)
    name = str(cfg.dataset.get("name") or "")
    root = str(cfg.dataset.get("root") or "")
    where = f"dataset={name}" + (f" (dataset.root={root})" if root else "")
    fix = (f"expected the data it was fitted on (dataset={own or name}, a dataset.root holding {fitted.scenes[0]!r}, "
           f"dataset.scenes=[{','.join(fitted.scenes)}] or left out); for another scene, fit a model on it (run) or "
           "fine-tune a generalizable one (finetune)")
    if own and name and own != name:
        raise ConfigError(f"{command}: {fitted.why}; it was fitted on dataset={own}, asked for "
                          f"{repr(asked) if asked else 'a scene'} of {where}; {fix}")
    changed = changed_content_key(cfg, trained)
    if changed is not None:
        key, was, now = changed
        raise ConfigError(f"{command}: {fitted.why}; it was fitted with dataset.{key}={was}, and dataset.{key}={now} "
                          f"makes other scenes under the same names; drop dataset.{key}={now}, or fit a model on "
                          "those scenes (run)")
    try:
        offered = tuple(components.dataset.scenes("train"))
    except DataError as error:  # the fitted scene's folder (dataset.scenes) is not under this root
        raise ConfigError(f"{command}: {fitted.why}; {where} does not hold it ({str(error).splitlines()[0]}); "
                          f"{fix}") from None
    missing = [scene for scene in fitted.scenes if scene not in offered]
    if missing:
        shown = ", ".join(repr(s) for s in offered[:SHOWN]) + (f" (+{len(offered) - SHOWN} more)"
                                                                 if len(offered) > SHOWN else "")
        asked_text = repr(asked) if asked else (f"{offered[0]!r}" if len(offered) == 1 else "another scene")
        raise ConfigError(f"{command}: {fitted.why}; asked for {asked_text}: {where} holds "
                          f"{shown or 'no training scene'}, not {missing[0]!r}; {fix}")
