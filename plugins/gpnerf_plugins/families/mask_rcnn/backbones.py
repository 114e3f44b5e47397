"""The detector's backbone: ResNet-34, Swin-T (``swin.py``) or torchvision's ResNet-50 (for its COCO weights), each with an FPN (the project's ``FPN``: 1x1 laterals,
top-down nearest-upsample-and-add, 3x3 outputs) and a max-pooled P6 for the RPN (torchvision's ``LastLevelMaxPool``).

The ResNet is torchvision's ResNet-34 (zero padding, a 3x3 max-pool after the stem) with GroupNorm of 32 groups in
place of BatchNorm: the norm of Mask R-CNN trained from scratch (Wu and He, ECCV 2018; He et al., "Rethinking
ImageNet Pre-training", 2019), which one frame a step cannot feed BatchNorm statistics. The project's extractor
blocks do not fit: their reflect padding fails on the one-cell-high C5 of a 32-pixel frame, and InstanceNorm
normalises each 3 x 4 C5 map on its own.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError
from gpnerf_plugins.extractors.fpn import FPN
from gpnerf_plugins.families.mask_rcnn.swin import SwinTransformer

RESNET34_BLOCKS = (3, 4, 6, 3)
RESNET50_BLOCKS = (3, 4, 6, 3)
RESNET_WIDTHS = (64, 128, 256, 512)
STRIDES = (4, 8, 16, 32, 64)
"""Pixels per cell of P2, P3, P4, P5 and P6."""


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(32, channels)


class BasicBlock(nn.Module):
    """Two 3x3 convs with GroupNorm and a residual (a 1x1 projection where the shape changes); the first conv carries
    the stride."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)
        self.bn1 = group_norm(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.bn2 = group_norm(out_channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False),
                                            group_norm(out_channels))

    def forward(self, x: Tensor) -> Tensor:
        out = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        return F.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet34(nn.Module):
    """ResNet-34: a 7x7 stride-2 stem and a 3x3 stride-2 max-pool, then four stages of 3, 4, 6, 3 basic blocks of 64,
    128, 256, 512 channels (stages 2-4 start with stride 2).

    Returns C2-C5 at strides 4, 8, 16, 32 (``channels``)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = group_norm(64)
        stages, previous = [], 64
        for i, (blocks, width) in enumerate(zip(RESNET34_BLOCKS, RESNET_WIDTHS)):
            stages.append(nn.Sequential(BasicBlock(previous, width, stride=1 if i == 0 else 2),
                                        *(BasicBlock(width, width) for _ in range(1, blocks))))
            previous = width
        self.stages = nn.ModuleList(stages)
        self.channels = list(RESNET_WIDTHS)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, images: Tensor) -> list[Tensor]:
        """``[N, 3, H, W]`` (H, W multiples of 32) -> C2..C5 ``[N, c_k, H / 2^(k+2), W / 2^(k+2)]``."""
        x = F.max_pool2d(F.relu(self.bn1(self.conv1(images))), 3, stride=2, padding=1)
        taps = []
        for stage in self.stages:
            x = stage(x)
            taps.append(x)
        return taps


class FrozenBatchNorm2d(nn.Module):
    """BatchNorm with fixed statistics and affine parameters (torchvision's ``FrozenBatchNorm2d``, eps 1e-5): what a
    torchvision detection checkpoint's ResNet-50 holds in its ``bn`` buffers."""

    def __init__(self, channels: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = eps
        for name, value in (("weight", 1.0), ("bias", 0.0), ("running_mean", 0.0), ("running_var", 1.0)):
            self.register_buffer(name, torch.full((channels,), value))

    def forward(self, x: Tensor) -> Tensor:
        scale = self.weight * (self.running_var + self.eps).rsqrt()
        return x * scale[None, :, None, None] + (self.bias - self.running_mean * scale)[None, :, None, None]


class Bottleneck(nn.Module):
    """ResNet-50's block as torchvision builds it (the stride on the 3x3 conv), its norms frozen."""

    def __init__(self, in_channels: int, width: int, stride: int) -> None:
        super().__init__()
        out = width * 4
        self.conv1 = nn.Conv2d(in_channels, width, 1, bias=False)
        self.bn1 = FrozenBatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride=stride, padding=1, bias=False)
        self.bn2 = FrozenBatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out, 1, bias=False)
        self.bn3 = FrozenBatchNorm2d(out)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out:
            self.downsample = nn.Sequential(nn.Conv2d(in_channels, out, 1, stride=stride, bias=False),
                                            FrozenBatchNorm2d(out))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNet50(nn.Module):
    """torchvision's ResNet-50 with frozen BatchNorm, the backbone of its ``maskrcnn_resnet50_fpn``, with its module
    names (``conv1``, ``bn1``, ``layer1``-``layer4``), so its COCO checkpoint maps key for key (``torchvision_keys.py``).
    Returns C2-C5 at strides 4-32 with 256, 512, 1024, 2048 channels."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = FrozenBatchNorm2d(64)
        previous = 64
        for i, (blocks, width) in enumerate(zip(RESNET50_BLOCKS, RESNET_WIDTHS)):
            layer = [Bottleneck(previous, width, 1 if i == 0 else 2)]
            layer += [Bottleneck(width * 4, width, 1) for _ in range(1, blocks)]
            setattr(self, f"layer{i + 1}", nn.Sequential(*layer))
            previous = width * 4
        self.channels = [w * 4 for w in RESNET_WIDTHS]

    def forward(self, images: Tensor) -> list[Tensor]:
        x = F.max_pool2d(F.relu(self.bn1(self.conv1(images))), 3, stride=2, padding=1)
        taps = []
        for i in range(4):
            x = getattr(self, f"layer{i + 1}")(x)
            taps.append(x)
        return taps


class BackboneFPN(nn.Module):
    """A backbone's C2-C5 through an FPN, plus P6 = max-pool(P5, 1, stride 2).

    Args:
        backbone: ``resnet34``, ``resnet50`` (torchvision's, frozen BatchNorm: for its COCO weights) or ``swin_t``;
            channels: the FPN's (256 in Mask R-CNN); drop_path: Swin-T's
            stochastic depth rate.
    """

    def __init__(self, backbone: str, channels: int, drop_path: float) -> None:
        super().__init__()
        if backbone == "resnet34":
            self.body: nn.Module = ResNet34()
        elif backbone == "resnet50":
            self.body = ResNet50()
        elif backbone == "swin_t":
            self.body = SwinTransformer(drop_path=drop_path)
        else:
            raise ConfigError(f"model.backbone={backbone!r}: expected resnet34, resnet50 or swin_t")
        self.fpn = FPN(self.body.channels, channels)
        self.strides = list(STRIDES)

    def forward(self, images: Tensor) -> list[Tensor]:
        """``[N, 3, H, W]`` -> P2..P6 ``[N, channels, H / s, W / s]`` for ``s`` in ``strides``."""
        levels = self.fpn(self.body(images))
        return levels + [F.max_pool2d(levels[-1], 1, 2)]
