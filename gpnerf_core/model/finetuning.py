"""Starting a fine-tuning from a generalized checkpoint's weights, when the new dataset may have another class count."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.model.checkpoint import (
    MODEL_SECTIONS,
    NOT_MODEL_KEYS,
    config_differences,
    format_differences,
    load_weights,
)


def finetune_weights(
    model: torch.nn.Module, state: Mapping[str, torch.Tensor], path: Path, old_config: str, new_config: str
) -> list[str]:
    """Load a checkpoint's weights for fine-tuning; returns the head tensors re-initialised for a new class count.

    A head tensor whose shape differs only because the class count changed keeps the fresh initialisation; any
    other difference is a ConfigError naming the config keys that differ from the checkpoint's.
    """
    own = model.state_dict()
    reinitialised = []
    for key, value in state.items():
        if key in own and tuple(own[key].shape) != tuple(value.shape):
            if key.startswith("head.") and tuple(own[key].shape[1:]) == tuple(value.shape[1:]):
                reinitialised.append(key)
                continue
            differences = config_differences(old_config, new_config, MODEL_SECTIONS, NOT_MODEL_KEYS)
            raise ConfigError(
                f"finetune checkpoint={path}: tensor {key!r} has shape {list(value.shape)}, this model "
                f"{list(own[key].shape)}; the model config differs from the checkpoint's: "
                f"{format_differences(differences) or 'no key (a different plugin version?)'}"
            )
    kept = {key: value for key, value in state.items() if key not in reinitialised}
    kept.update({key: own[key] for key in reinitialised})
    load_weights(model, kept, f"checkpoint {path}")
    return reinitialised
