"""``open_clip`` and ``timm``: a CLIP-like or timm image model built from a local weights file when its package is
installed (nothing is downloaded). Each gives the model's patch tokens as a map (CLIP's through its projection, in the
space of its text embeddings, MaskCLIP-style), resized to one cell per ``stride`` pixels and L2-normalised per cell.

Neither package installs beside gpnerf-core's CPU torch here (they need torchvision, docs/install.md); without it the
provider refuses in one line naming the package and the weights file it would read.
"""

from __future__ import annotations

from abc import abstractmethod

from dataclasses import dataclass, field
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError, FeatureProvider
from gpnerf_plugins.feature_providers.common import file_hash, package_version, require_package, weights_file

OPEN_CLIP_INSTALL = "pip install open_clip_torch (with torchvision built for your torch)"
TIMM_INSTALL = "pip install timm (with torchvision built for your torch)"
CLIP_MEAN, CLIP_STD = (0.48145466, 0.4578275, 0.40821073), (0.26862954, 0.26130258, 0.27577711)


@dataclass
class OpenClipProviderConfig:
    name: str = "open_clip"
    """Registry name and Hydra option (+feature_provider=open_clip)."""
    model: str = "ViT-B-16"
    """open_clip architecture name (open_clip.list_models())."""
    weights: str = ""
    """Local weights file of that architecture (open_clip's pretrained= file path); required, nothing is downloaded."""
    input_size: list[int] = field(default_factory=lambda: [224, 224])
    """[height, width] the frame is resized to before the model (a multiple of the patch size)."""
    stride: int = 8
    """Image pixels per feature cell of the frame: the patch-token map is resized (bilinear) to the frame over it."""


@dataclass
class TimmProviderConfig:
    name: str = "timm"
    """Registry name and Hydra option (+feature_provider=timm)."""
    model: str = "vit_small_patch14_dinov2"
    """timm architecture name (timm.list_models())."""
    weights: str = ""
    """Local weights file (a state dict: .pth, .bin or .safetensors); required, nothing is downloaded."""
    input_size: list[int] = field(default_factory=lambda: [224, 224])
    """[height, width] the frame is resized to before the model."""
    stride: int = 8
    """Image pixels per feature cell of the frame: the model's map is resized (bilinear) to the frame over it."""


def checked_size(size: Sequence[int]) -> tuple[int, int]:
    if len(size) != 2 or any(int(s) < 1 for s in size):
        raise ConfigError(f"feature_provider.input_size={list(size)}; expected [height, width], positive pixels")
    return int(size[0]), int(size[1])


def tokens_to_map(tokens: Tensor, grid: tuple[int, int]) -> Tensor:
    """``[B, N, C]`` patch tokens (prefix tokens removed) -> ``[B, C, gh, gw]``."""
    return tokens.transpose(1, 2).reshape(tokens.shape[0], tokens.shape[2], *grid)


class _HubProvider(nn.Module, FeatureProvider):
    """What both share: resize and normalise the frame, run ``_map``, resize to the frame over ``stride``, L2."""

    mean: tuple[float, float, float] = CLIP_MEAN
    std: tuple[float, float, float] = CLIP_STD

    def __init__(self, stride: int, input_size: Sequence[int]) -> None:
        super().__init__()
        if stride < 1:
            raise ConfigError(f"feature_provider.stride={stride}; expected a positive number of pixels per cell")
        self.stride = int(stride)
        self.input_size = checked_size(input_size)
        self._fingerprint = ""

    def fingerprint(self) -> str:
        return self._fingerprint

    def train(self, mode: bool = True) -> "_HubProvider":
        return super().train(False)  # frozen: always in eval mode

    @abstractmethod
    def _map(self, x: Tensor) -> Tensor:
        """``[B, 3, h, w]`` normalised frames at ``input_size`` -> ``[B, C, gh, gw]`` the model's feature map."""

    @torch.no_grad()
    def compute(self, scene: str, frames: Sequence[int], images: Tensor) -> Tensor:
        self.to(images.device)
        x = F.interpolate(images.float(), size=self.input_size, mode="bicubic", align_corners=False).clamp(0, 1)
        mean = torch.tensor(self.mean, device=x.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=x.device).view(1, 3, 1, 1)
        maps = self._map((x - mean) / std)
        cells = self.feature_size(int(images.shape[-2]), int(images.shape[-1]))
        maps = F.interpolate(maps, size=cells, mode="bilinear", align_corners=False)
        return F.normalize(maps, dim=1).float()


class OpenClipProvider(_HubProvider):
    """An open_clip ViT's patch tokens through ``ln_post`` and the projection (MaskCLIP's dense CLIP features): in the
    space of ``encode_text``'s embeddings, so a text query compares with every cell."""

    text_encoder = True

    def __init__(self, *, model: str, weights: str, input_size: Sequence[int], stride: int) -> None:
        super().__init__(stride, input_size)
        require_package("open_clip", "open_clip", OPEN_CLIP_INSTALL, weights or "(feature_provider.weights is empty)")
        path = weights_file(weights, "feature_provider.weights", "open_clip", OPEN_CLIP_INSTALL)
        import open_clip

        self.model = open_clip.create_model(model, pretrained=str(path)).eval().requires_grad_(False)
        self.tokenizer = open_clip.get_tokenizer(model)
        visual = self.model.visual
        if not hasattr(visual, "output_tokens"):
            raise ConfigError(f"feature_provider.model={model}: not a vision transformer (no patch tokens); the "
                              "open_clip provider reads a ViT's patch tokens")
        visual.output_tokens = True
        self.channels = int(getattr(self.model, "embed_dim", 0) or visual.output_dim)
        self._fingerprint = (f"open_clip|{package_version('open_clip_torch')}|{model}|weights {file_hash(path)}|"
                             f"input {self.input_size}|stride {self.stride}")

    def _map(self, x: Tensor) -> Tensor:
        visual = self.model.visual
        _, tokens = visual(x)  # [B, N, width] patch tokens
        if tokens.shape[-1] != self.channels:
            tokens = visual.ln_post(tokens) @ visual.proj
        patch = visual.patch_size if isinstance(visual.patch_size, tuple) else (visual.patch_size,) * 2
        return tokens_to_map(tokens, (x.shape[-2] // patch[0], x.shape[-1] // patch[1]))

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> Tensor:
        tokens = self.tokenizer(list(texts))
        return F.normalize(self.model.encode_text(tokens).float(), dim=-1)


class TimmProvider(_HubProvider):
    """A timm model's last feature map (``forward_features``: a CNN's ``[B, C, h, w]``, a ViT's patch tokens without
    its prefix tokens); no text encoder."""

    def __init__(self, *, model: str, weights: str, input_size: Sequence[int], stride: int) -> None:
        super().__init__(stride, input_size)
        require_package("timm", "timm", TIMM_INSTALL, weights or "(feature_provider.weights is empty)")
        path = weights_file(weights, "feature_provider.weights", "timm", TIMM_INSTALL)
        import timm

        kwargs = {"img_size": self.input_size} if "vit" in model else {}
        self.model = timm.create_model(model, pretrained=False, num_classes=0, **kwargs)
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
        try:
            self.model.load_state_dict(state, strict=False)
        except RuntimeError as exc:
            raise ConfigError(f"{path}: not weights of timm model {model!r} ({str(exc).splitlines()[0][:200]})") from None
        self.model.eval().requires_grad_(False)
        config = getattr(self.model, "pretrained_cfg", {}) or {}
        self.mean = tuple(config.get("mean", CLIP_MEAN))
        self.std = tuple(config.get("std", CLIP_STD))
        self.channels = int(self.model.num_features)
        self._fingerprint = (f"timm|{package_version('timm')}|{model}|weights {file_hash(path)}|"
                             f"input {self.input_size}|stride {self.stride}")

    def _map(self, x: Tensor) -> Tensor:
        out = self.model.forward_features(x)
        if out.dim() == 4:
            return out
        tokens = out[:, int(getattr(self.model, "num_prefix_tokens", 1)):]
        grid = self.model.patch_embed.grid_size
        return tokens_to_map(tokens, (int(grid[0]), int(grid[1])))
