"""Checkpoints that resume exactly: model, optimizer, schedule, step, random state, config and versions."""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Any

import torch

from gpnerf_core.errors import DataError
from gpnerf_core.io import atomic_torch_save

FORMAT_VERSION = 1


def software_versions() -> dict[str, str]:
    from gpnerf_core import __version__
    from gpnerf_core.registry import get_registry

    versions = {"gpnerf_core": __version__, "torch": torch.__version__, "python": platform.python_version()}
    versions.update({f"plugin:{name}": v for name, v in get_registry().plugin_versions.items()})
    return versions


def save_checkpoint(
    path: Path,
    *,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    step: int,
    generator: torch.Generator,
    history: list[dict[str, float]],
    elapsed: float,
    config_yaml: str,
) -> None:
    state = {
        "format": FORMAT_VERSION,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "step": step,
        "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(),
        "history": history,
        "elapsed": elapsed,
        "config": config_yaml,
        "versions": software_versions(),
    }
    atomic_torch_save(path, state)


def load_checkpoint(
    path: Path, model: torch.nn.Module, *, optimizer: Any = None, scheduler: Any = None
) -> dict[str, Any]:
    """Load ``path`` into ``model`` (and optimizer/scheduler when given); restores the global torch RNG."""
    if not path.is_file():
        raise DataError(f"checkpoint {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise DataError(f"checkpoint {path} could not be read: {type(exc).__name__}: {exc}") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT_VERSION:
        raise DataError(f"checkpoint {path} is not a gpnerf-core checkpoint of format {FORMAT_VERSION}")
    missing, unexpected = model.load_state_dict(state["model"], strict=False)
    if missing or unexpected:
        raise DataError(
            f"checkpoint {path} does not match the configured model: missing {missing[:3]}, unexpected {unexpected[:3]}"
        )
    if optimizer is not None:
        optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None:
        scheduler.load_state_dict(state["scheduler"])
    torch.set_rng_state(state["torch_rng"])
    return state
