"""What a model computes from its source views, kept between renders of one scene: a trajectory (``render``), a
moving camera (``view``), the held-out views of a scene (``export``).

A family says what it can reuse (``Capabilities.source_encoding``): encoded feature maps of each source frame, kept per
(model state, scene, frame), so each source frame is encoded once (``PER_VIEW``); or what it computes from a whole set
of source views together (a feed-forward Gaussian family's Gaussians), kept per (model state, scene, frame set)
(``SOURCE_SET``). ``for_sources`` serves either.

The model state is the model object and the version counters of its parameters and buffers: an optimizer step, a
``load_state_dict`` or any in-place change of a weight bumps a counter, so features of old weights are never
returned. Entries are evicted least recently used first once their bytes exceed the budget.

Features are encoded for the missing frames of a request in one batch; the encoder treats the frames of a batch
independently (its normalisations are per image in inference), so a cached map equals the one an uncached
``predict`` computes up to floating-point reassociation of batched convolutions (``tests/test_feature_cache.py``:
colour, depth and rendered features within 1e-4 (measured ~1e-5), logits 1e-3, the same classes).
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.model import SourceEncoding
from gpnerf_core.types import FeatureMaps, SourceViews


@dataclass
class CacheStats:
    """Frames served from the cache (hits) and encoded (misses), and the bytes held."""

    hits: int = 0
    misses: int = 0
    bytes: int = 0


def model_state(model: nn.Module) -> tuple[int, ...]:
    """A token that changes whenever a parameter or buffer of ``model`` is changed in place or replaced, or the model
    switches between training and inference mode (normalisations behave differently)."""
    parameters = list(model.parameters())  # one walk of the module tree (a viewer frame asks once: ~0.4 ms a walk)
    return (id(model), int(model.training), *(t._version for t in parameters), *(id(t) for t in parameters),
            *(t._version for t in model.buffers()))


class SourceFeatureCache:
    """What models compute from source frames, under a memory budget.

    Args:
        budget_mb: the most megabytes kept (the radiance and semantic maps of every cached frame, and the tensors of
            every cached source-set encoding).
    """

    def __init__(self, budget_mb: float = 512.0) -> None:
        if not budget_mb > 0:
            raise ConfigError(f"feature cache budget {budget_mb} MB: expected a positive size")
        self.budget = int(budget_mb * 2**20)
        self.stats = CacheStats()
        self._entries: OrderedDict[tuple, Any] = OrderedDict()

    def for_sources(self, model: nn.Module, scene: str, frames: Sequence[int], sources: SourceViews, *,
                    near: float, far: float) -> Any:
        """What ``model.predict`` reuses for ``sources`` (frames ``frames`` of ``scene``, depth bounds ``near`` /
        ``far``): the frames' ``features`` for a ``PER_VIEW`` family, the set's ``source_set`` for a ``SOURCE_SET``
        one."""
        if model.capabilities.source_encoding is SourceEncoding.SOURCE_SET:
            return self.source_set(model, scene, frames, sources, near=near, far=far)
        return self.features(model, scene, frames, sources.rgb)

    def source_set(self, model: nn.Module, scene: str, frames: Sequence[int], sources: SourceViews, *,
                   near: float, far: float) -> Any:
        """``model.encode_sources(sources, near=near, far=far)`` of frames ``frames`` of ``scene``, computed once per
        model state, frame set (in order), image size and depth bounds; one hit or miss per request."""
        if len(frames) != sources.num_views:
            raise ConfigError(f"{len(frames)} frame indices for {sources.num_views} source views; "
                              "expected one per view")
        key = ("set", model_state(model), scene, tuple(int(f) for f in frames), tuple(sources.rgb.shape[1:]),
               str(sources.rgb.device), float(near), float(far))
        if key in self._entries:
            self.stats.hits += 1
        else:
            with torch.inference_mode():
                self._store(key, model.encode_sources(sources, near=near, far=far))
            self.stats.misses += 1
        self._entries.move_to_end(key)
        self._evict(keep={key})
        return self._entries[key]

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


def _size(value: Any) -> int:
    """Bytes of the tensors in ``value``: a tensor, or tensors inside tuples, lists, dicts and dataclasses."""
    if isinstance(value, Tensor):
        return value.numel() * value.element_size()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return sum(_size(getattr(value, f.name)) for f in dataclasses.fields(value))
    if isinstance(value, dict):
        return sum(_size(v) for v in value.values())
    if isinstance(value, (tuple, list)):
        return sum(_size(v) for v in value)
    return 0
