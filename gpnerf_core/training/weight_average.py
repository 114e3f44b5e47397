"""An exponential moving average of a model's weights, evaluated in place of the last step's weights.

With ``train.ema_decay = d`` every optimizer step moves the average towards the new weights by ``1 - d_t`` where
``d_t = min(d, (1 + t) / (10 + t))`` after ``t`` updates: early on the average follows the weights closely, so a
short run is not dominated by its random initialisation. Integer buffers (counters) are copied, not averaged.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator, Mapping

import torch
from torch import Tensor


class WeightAverage:
    """The running average of ``model``'s floating-point parameters and buffers.

    Args:
        model: the trained module (not a DDP wrapper: its state-dict keys are the checkpoint's).
        decay: the long-run decay ``d`` in (0, 1).
    """

    def __init__(self, model: torch.nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay {decay}: expected a value in (0, 1)")
        self.decay = decay
        self.updates = 0
        self.average: dict[str, Tensor] = {key: value.detach().clone() for key, value in model.state_dict().items()}

    def current_decay(self) -> float:
        return min(self.decay, (1.0 + self.updates) / (10.0 + self.updates))

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        """Move the average towards ``model``'s current weights (call after each optimizer step)."""
        weight = 1.0 - self.current_decay()
        for key, value in model.state_dict().items():
            average = self.average[key]
            if average.is_floating_point():
                average.lerp_(value.detach(), weight)
            else:
                average.copy_(value)
        self.updates += 1

    def state_dict(self) -> dict[str, Any]:
        return {"decay": self.decay, "updates": self.updates, "weights": self.average}

    def load_state_dict(self, state: Mapping[str, Any], source: str) -> None:
        """Restore an average written by ``state_dict``; ``source`` names the file in errors."""
        weights = state["weights"]
        if set(weights) != set(self.average):
            raise ValueError(f"{source}: its weight average holds other tensors than this model")
        for key, value in weights.items():
            if tuple(value.shape) != tuple(self.average[key].shape):
                raise ValueError(f"{source}: tensor {key!r} of its weight average has shape {list(value.shape)}, the "
                                 f"configured model expects {list(self.average[key].shape)}")
        self.average = {key: value.to(self.average[key].device).clone() for key, value in weights.items()}
        self.updates = int(state["updates"])

    @contextmanager
    def swapped_in(self, model: torch.nn.Module) -> Iterator[None]:
        """Within the block ``model`` holds the averaged weights; its trained weights come back after."""
        trained = {key: value.detach().clone() for key, value in model.state_dict().items()}
        model.load_state_dict(self.average)
        try:
            yield
        finally:
            model.load_state_dict(trained)
