"""Interface of a feature provider: a frozen 2D model that gives every frame of a scene a dense feature map."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Sequence

from torch import Tensor

from gpnerf_core.errors import ConfigError


class FeatureProvider(ABC):
    """A frozen 2D model's dense features of a frame, ``[C, h, w]``: what a feature field distils and what queries
    compare against (``+feature_provider=<name>``; XFeat's descriptors, a user's CLIP or LSeg maps, a trained
    checkpoint's own extractor).

    A provider is frozen and deterministic: the same frame always gives the same features, so they are computed once
    per (provider, its config, frame) and kept on disk (``gpnerf_core.features``: ``frame_features`` reads them
    through the cache). Everything its output depends on is in ``fingerprint()``, which keys that cache. It may be an
    ``nn.Module`` (then kept in eval mode, without gradients) or hold no parameters at all (``files``).

    Attributes:
        channels: C, the number of feature channels of ``compute``'s maps.
        stride: image pixels per feature cell at the size a frame is given at: a frame ``H x W`` gives a map of
            ``round(H / stride) x round(W / stride)`` cells (at least 1 each); XFeat's is 8.
        text_encoder: True when ``encode_text`` embeds text into the same C channels (a CLIP-like provider).
    """

    channels: int
    stride: int
    text_encoder: bool = False

    @abstractmethod
    def fingerprint(self) -> str:
        """Everything the features depend on, as one string: the provider's name, its config values and its weights
        (a weights file's hash or the package's version). The cache key includes it, so a changed config or changed
        weights never read features computed before."""

    @abstractmethod
    def compute(self, scene: str, frames: Sequence[int], images: Tensor) -> Tensor:
        """The features of ``frames`` of ``scene``.

        Args:
            scene: the scene's name in its dataset (a provider reading its own files looks them up by it).
            frames: the frame indices in the scene, one per image.
            images: ``[B, 3, H, W]`` float32 RGB in [0, 1], B = ``len(frames)``, at the size the dataset loads frames
                at (a provider that reads stored features, ``files``, may ignore them).

        Returns:
            ``[B, C, h, w]`` float32, finite, C = ``channels``, ``h x w`` = the frame size over ``stride``
            (``feature_size``); on the images' device or the CPU.
        """

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """``[N, C]`` float32 embeddings of ``texts`` in the features' channels (a text query); a provider without a
        text encoder refuses naming itself."""
        raise ConfigError(f"feature provider {type(self).__name__} has no text encoder (text_encoder is False); "
                          "query by example, or use a provider with one (open_clip, or files with text embeddings)")

    def feature_size(self, height: int, width: int) -> tuple[int, int]:
        """``(h, w)``, the cells of the map of an ``height x width`` frame: each side over ``stride``, rounded, at
        least 1."""
        return max(1, round(height / self.stride)), max(1, round(width / self.stride))
