"""A trained model read back: one reader for every command that starts from a checkpoint.

``load_trained(path)`` reads a checkpoint and checks its content hash. Whoever reads it hands the read on, so that a
command reads its file once: the launcher that composes ``eval``'s config from the checkpoint's overrides hands it to
the job (``engine.launching.Handover``), ``plan_resume`` to the trainer (``ResumePlan.take_read``). Nothing here keeps a
read: its tensors go when its last holder lets go of it. A trained model is opened one way, ``engine.opening
.open_trained``, which restores the checkpoint's model settings into the command's config (``restore_model_settings``:
a default that changed since must not change a trained model).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch
import yaml
from omegaconf import DictConfig, OmegaConf, open_dict

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

    @property
    def family(self) -> str:
        """The model family it trained (``model.name``; ``gnt`` for a checkpoint written before there were others)."""
        from gpnerf_core.config.legacy import DEFAULT_MODEL

        return str(((yaml.safe_load(self.config_yaml) or {}).get("model") or {}).get("name") or DEFAULT_MODEL)


def load_trained(path: str | Path, key: str = "checkpoint") -> TrainedModel:
    """The trained model in ``path``, read and verified (its content hash); each call reads the file, so a caller
    hands its read on instead of asking again.

    Args:
        key: the option that named ``path`` (``checkpoint``, ``train.resume``), for the error lines.

    Raises:
        DataError: empty, missing, a folder, unreadable, of another format version, or damaged (content hash).
    """
    path = checked_checkpoint_path(path, key)
    return TrainedModel(path, read_checkpoint(path))


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
