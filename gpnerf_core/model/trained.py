"""A trained model read back: one reader for every command that starts from a checkpoint.

``load_trained(path)`` reads a checkpoint once (and checks its content hash once), whoever asks: the launcher that
composes ``eval``'s config from the checkpoint's overrides and the task that then evaluates it, ``plan_resume`` and the
trainer it hands over to, ``stress``, ``finetune``, ``render``, ``view`` and ``model.init``. The config of a trained
model is rebuilt one way, ``TrainedModel.config``: the checkpoint's overrides, then the command's, composed; then
the checkpoint's model settings restored wherever the command did not set them (a default that changed since must
not change a trained model). A Hydra command composes the same overrides itself and calls ``restore_model_settings``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch
import yaml
from omegaconf import DictConfig, OmegaConf, open_dict

from gpnerf_core.config.compose import compose
from gpnerf_core.config.overrides import merge_overrides, override_key
from gpnerf_core.errors import DataError
from gpnerf_core.model.checkpoint import (
    ABSENT, checkpoint_sections, evaluation_weights, model_differences, read_checkpoint,
)
from gpnerf_core.model.classes import ClassList, checkpoint_classes


@dataclass(frozen=True)
class TrainedModel:
    """A checkpoint's contents, read and verified once.

    Attributes:
        path: the file.
        state: its dictionary (``model.checkpoint``), configs written by earlier versions brought to today's keys.
    """

    path: Path
    state: Mapping[str, Any]

    @property
    def step(self) -> int:
        return int(self.state["step"])

    @property
    def config_yaml(self) -> str:
        return str(self.state.get("config") or "")

    @property
    def config_sha256(self) -> str | None:
        return self.state.get("config_sha256")

    @property
    def overrides(self) -> list[str]:
        """The Hydra overrides that composed the trained config (as typed, run-specific ones included)."""
        return [str(o) for o in self.state.get("overrides") or []]

    @property
    def scenes(self) -> tuple[str, ...]:
        """The scenes the model was trained on: those the checkpoint records, or for one written before they were, its
        config's ``dataset.scenes`` (empty when neither names any)."""
        recorded = self.state.get("scenes")
        if isinstance(recorded, (list, tuple)) and recorded:
            return tuple(str(name) for name in recorded)
        dataset = (yaml.safe_load(self.config_yaml) or {}).get("dataset") or {}
        chosen = dataset.get("scenes") if isinstance(dataset, dict) else None
        return tuple(str(name) for name in chosen) if isinstance(chosen, list) else ()

    @property
    def model_sections(self) -> tuple[str, ...]:
        """The config sections that define the trained model (``checkpoint_sections``)."""
        return checkpoint_sections(self.state)

    @property
    def classes(self) -> ClassList | None:
        """The classes the model was trained with (None: a checkpoint written before they were stored)."""
        return checkpoint_classes(self.state, self.path)

    def weights(self, choice: str = "average") -> tuple[dict[str, torch.Tensor], str]:
        """The model weights to evaluate or start from: ``(state dict, "average" | "trained")`` (``eval.weights``)."""
        return evaluation_weights(self.state, choice)

    def config(self, overrides: list[str] | tuple[str, ...] = ()) -> DictConfig:
        """The trained model's config with ``overrides`` on top: composed from the checkpoint's overrides and then
        ``overrides``, the model settings restored (``restore_model_settings``)."""
        cfg = compose(merge_overrides(self.overrides, list(overrides)))
        restore_model_settings(cfg, self, [override_key(o) for o in overrides])
        return cfg


_LAST: tuple[tuple[Any, ...], TrainedModel] | None = None
"""The last checkpoint read, by file identity: the launcher's read serves the task, ``plan_resume``'s the trainer."""


def load_trained(path: str | Path, key: str = "checkpoint") -> TrainedModel:
    """The trained model in ``path``, read and verified once per file (the same file read again is not read).

    Args:
        key: the option that named ``path`` (``checkpoint``, ``train.resume``), for the error lines.

    Raises:
        DataError: empty, missing, a folder, unreadable, of another format version, or damaged (content hash).
    """
    global _LAST
    path = checked_checkpoint_path(path, key)
    identity = _identity(path)
    if _LAST is not None and identity is not None and _LAST[0] == identity:
        return _LAST[1]
    trained = TrainedModel(path, read_checkpoint(path))
    _LAST = (identity, trained) if identity is not None else None
    return trained


def checked_checkpoint_path(value: str | Path, key: str = "checkpoint") -> Path:
    """``value`` as the path of a checkpoint file; an empty value, a folder (naming the newest checkpoint in it, if
    any) and a missing file are each one ``DataError`` naming ``key``."""
    text = str(value).strip()
    if not text or text == ".":
        raise DataError(f"{key}= is empty; expected {key}=<path to a .pt file written by run, in <run>/checkpoints/>")
    path = Path(value)
    if path.is_dir():
        newest = newest_checkpoint_file(path)
        if newest is None:
            raise DataError(f"{key}={path} is a folder, with no checkpoint in it; expected a .pt file written by run "
                            "(e.g. <run>/checkpoints/step_XXXXXXX.pt)")
        raise DataError(f"{key}={path} is a folder; expected a .pt file (e.g. {newest}, the newest checkpoint in it)")
    if not path.is_file():
        raise DataError(f"{key}={path}: no such file; expected a .pt file written by run (in <run>/checkpoints/)")
    return path


def newest_checkpoint_file(folder: Path) -> Path | None:
    """The newest ``step_<step>.pt`` in ``folder`` or in its ``checkpoints/`` (None: none)."""
    found = [p for where in (folder, folder / "checkpoints") for p in where.glob("step_*.pt") if p.is_file()]
    steps = [(int(p.stem[5:]), p) for p in found if p.stem[5:].isdigit()]
    return max(steps)[1] if steps else None


def release_trained() -> None:
    """Forget the last checkpoint read (its tensors), once its weights are in a model."""
    global _LAST
    _LAST = None


def _identity(path: Path) -> tuple[Any, ...] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return (str(path.resolve()), stat.st_ino, stat.st_size, stat.st_mtime_ns)


def restore_model_settings(cfg: DictConfig, trained: TrainedModel, typed: list[str]) -> list[str]:
    """Give ``cfg`` the checkpoint's model and loss settings wherever the command did not set them (``typed``: the
    dotted keys it set). Returns the notes on restored keys (empty when nothing changed).

    A command's config is composed from the checkpoint's overrides plus its own; if a default changed since the
    checkpoint was written, the recomposed model would differ from the trained one. Such keys are set back to the
    checkpoint's values (and reported); keys the command set keep its value.
    """
    current = OmegaConf.to_yaml(cfg, resolve=True)
    restored, dropped = [], []
    for key, old, new in model_differences(trained.config_yaml, current, trained.model_sections):
        if any(key == t or key.startswith(t + ".") for t in typed):
            continue
        if new == ABSENT:  # an option of the checkpoint this version no longer has
            dropped.append(key)
            continue
        with open_dict(cfg):
            OmegaConf.update(cfg, key, old, merge=False)
        restored.append(key)
    notes = []
    if restored:
        notes.append(f"kept the checkpoint's value of {', '.join(restored)} (the defaults changed since it was written)")
    if dropped:
        notes.append(f"the checkpoint's {', '.join(dropped)} is no option of this version (left out)")
    return notes
