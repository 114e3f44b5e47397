"""Encoded source-view feature maps kept per (model state, scene, frame), so many renders of one scene encode each
source frame once: a trajectory (``render``), a moving camera (``view``), the held-out views of a scene.

The model state is the model object and the version counters of its parameters and buffers: an optimizer step, a
``load_state_dict`` or any in-place change of a weight bumps a counter, so features of old weights are never
returned. Entries are evicted least recently used first once their bytes exceed the budget.

Features are encoded for the missing frames of a request in one batch; the encoder treats the frames of a batch
independently (its normalisations are per image in inference), so a cached map equals the one an uncached
``predict`` computes up to floating-point reassociation of batched convolutions (``tests/test_feature_cache.py``:
colour, depth and rendered features within 1e-4 (measured ~1e-5), logits 1e-3, the same classes).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError
from gpnerf_core.types import FeatureMaps


@dataclass
class CacheStats:
    """Frames served from the cache (hits) and encoded (misses), and the bytes held."""

    hits: int = 0
    misses: int = 0
    bytes: int = 0


def model_state(model: nn.Module) -> tuple[int, ...]:
    """A token that changes whenever a parameter or buffer of ``model`` is changed in place or replaced, or the model
    switches between training and inference mode (normalisations behave differently)."""
    return (id(model), int(model.training), *(t._version for t in model.parameters()),
            *(id(t) for t in model.parameters()), *(t._version for t in model.buffers()))


class SourceFeatureCache:
    """Feature maps of source frames under a memory budget.

    Args:
        budget_mb: the most megabytes of feature maps kept (radiance and semantic maps of every cached frame).
    """

    def __init__(self, budget_mb: float = 512.0) -> None:
        if not budget_mb > 0:
            raise ConfigError(f"feature cache budget {budget_mb} MB: expected a positive size")
        self.budget = int(budget_mb * 2**20)
        self.stats = CacheStats()
        self._entries: OrderedDict[tuple, tuple[Tensor, Tensor | None]] = OrderedDict()

    def features(self, model: nn.Module, scene: str, frames: Sequence[int], images: Tensor) -> FeatureMaps:
        """The feature maps of ``frames`` of ``scene`` (``images``: their ``[V, 3, H, W]`` pictures, used for the
        frames not cached), in the order given; the model must provide ``encode(images) -> FeatureMaps``."""
        if len(frames) != images.shape[0]:
            raise ConfigError(f"{len(frames)} frame indices for {images.shape[0]} images; expected one per image")
        state = model_state(model)
        keys = [(state, scene, int(f), tuple(images.shape[1:]), str(images.device)) for f in frames]
        missing = [i for i, key in enumerate(keys) if key not in self._entries]
        if missing:
            with torch.inference_mode():
                encoded = model.encode(images[missing])
            for row, i in enumerate(missing):
                semantic = encoded.semantic[row : row + 1].clone() if encoded.semantic is not None else None
                self._store(keys[i], (encoded.radiance[row : row + 1].clone(), semantic))
        self.stats.misses += len(set(missing))
        self.stats.hits += len(frames) - len(missing)
        for key in keys:
            self._entries.move_to_end(key)
        radiance = torch.cat([self._entries[key][0] for key in keys])
        semantics = [self._entries[key][1] for key in keys]
        semantic = None if semantics[0] is None else torch.cat(semantics)  # type: ignore[arg-type]
        self._evict(keep=set(keys))
        return FeatureMaps(radiance=radiance, semantic=semantic)

    def clear(self) -> None:
        self._entries.clear()
        self.stats.bytes = 0

    def __len__(self) -> int:
        return len(self._entries)

    def _store(self, key: tuple, value: tuple[Tensor, Tensor | None]) -> None:
        self._entries[key] = value
        self.stats.bytes += _size(value)

    def _evict(self, keep: set) -> None:
        """Drop least recently used entries over the budget (never those of the request just served)."""
        while self.stats.bytes > self.budget and self._entries:
            key = next(iter(self._entries))
            if key in keep:
                break
            self.stats.bytes -= _size(self._entries.pop(key))


def _size(value: tuple[Tensor, Tensor | None]) -> int:
    return sum(t.numel() * t.element_size() for t in value if t is not None)
