"""GNT's ResNet-34-style encoder (InstanceNorm, reflect padding, no max-pool) and its U-Net radiance decoder.

Submodule names follow GNT's ``feature_net`` state dict (``conv1``, ``bn1``, ``layer1.0.downsample.0``,
``upconv3.conv.conv``, ``out_conv``, ...), so a GNT checkpoint loads into ``ResUNet`` with the default widths.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _instance_norm(channels: int) -> nn.InstanceNorm2d:
    return nn.InstanceNorm2d(channels, affine=True, track_running_stats=False)


def _conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False, padding_mode="reflect")


class BasicBlock(nn.Module):
    """Two 3x3 convs with InstanceNorm and a residual; the first conv carries the stride."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = _conv3x3(in_channels, out_channels, stride)
        self.bn1 = _instance_norm(out_channels)
        self.conv2 = _conv3x3(out_channels, out_channels)
        self.bn2 = _instance_norm(out_channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False),
                _instance_norm(out_channels),
            )

    def forward(self, x: Tensor) -> Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return F.relu(out + identity)


def _make_layer(in_channels: int, out_channels: int, blocks: int) -> nn.Sequential:
    """``blocks`` BasicBlocks; the first halves the resolution (GNT puts the stride on every layer's first block)."""
    layers = [BasicBlock(in_channels, out_channels, stride=2)]
    layers += [BasicBlock(out_channels, out_channels) for _ in range(1, blocks)]
    return nn.Sequential(*layers)


class ConvNormELU(nn.Module):
    """Decoder conv: conv (with bias, reflect padding), InstanceNorm, ELU."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels, kernel_size, padding=(kernel_size - 1) // 2, padding_mode="reflect"
        )
        self.bn = _instance_norm(out_channels)

    def forward(self, x: Tensor) -> Tensor:
        return F.elu(self.bn(self.conv(x)))


class UpConvNormELU(nn.Module):
    """x2 bilinear upsampling (align_corners=True, as GNT) followed by a ``ConvNormELU``."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = ConvNormELU(in_channels, out_channels)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=True))


class ResUNet(nn.Module):
    """Encoder taps x0..x3 at strides 2/4/8/16 and the U-Net radiance map at stride 4.

    Args:
        widths: channels of the stem, layer1, layer2 and layer3 (GNT: 64, 64, 128, 256).
        blocks: BasicBlocks in layer1, layer2 and layer3 (ResNet-34: 3, 4, 6).
        radiance_dim: channels of the radiance map (GNT: 32).
    """

    def __init__(self, widths: list[int], blocks: list[int], radiance_dim: int) -> None:
        super().__init__()
        stem, w1, w2, w3 = widths
        self.widths = tuple(widths)
        self.conv1 = nn.Conv2d(3, stem, 7, stride=2, padding=3, bias=False, padding_mode="reflect")
        self.bn1 = _instance_norm(stem)
        self.layer1 = _make_layer(stem, w1, blocks[0])
        self.layer2 = _make_layer(w1, w2, blocks[1])
        self.layer3 = _make_layer(w2, w3, blocks[2])
        # Decoder widths follow the skip connections' widths (GNT: 128 and 64).
        self.upconv3 = UpConvNormELU(w3, w2)
        self.iconv3 = ConvNormELU(w2 + w2, w2)
        self.upconv2 = UpConvNormELU(w2, w1)
        self.iconv2 = ConvNormELU(w1 + w1, radiance_dim)
        self.out_conv = nn.Conv2d(radiance_dim, radiance_dim, 1)

    def encode(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``[N, 3, H, W]`` -> x0 ``[N, w0, H/2, W/2]``, x1 at H/4, x2 at H/8, x3 ``[N, w3, H/16, W/16]``."""
        x0 = F.relu(self.bn1(self.conv1(images)))
        x1 = self.layer1(x0)
        x2 = self.layer2(x1)
        x3 = self.layer3(x2)
        return x0, x1, x2, x3

    def decode(self, x1: Tensor, x2: Tensor, x3: Tensor) -> Tensor:
        """U-Net decoder: radiance map ``[N, radiance_dim, H/4, W/4]``.

        The concatenation order (upsampled path first, then the skip) is GNT's, which its weights need.
        """
        x = self.iconv3(torch.cat([self.upconv3(x3), x2], dim=1))
        x = self.iconv2(torch.cat([self.upconv2(x), x1], dim=1))
        return self.out_conv(x)
