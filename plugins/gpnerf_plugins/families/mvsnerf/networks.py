"""MVSNeRF's networks: the 3D U-Net that regularises the cost volume (``CostRegNet``) and the feature-modulated MLP
(``Renderer_ours``, "v0") with the semantic branch of "MVSNeRF + Semantic Head"."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

ENCODING_CHANNELS = 8
"""Channels of the encoding volume (MVSNeRF's neural encoding volume)."""
LEVELS = 3
"""Stride-2 levels of the 3D U-Net: every side of its input must be a multiple of 2**LEVELS."""
FREQUENCIES = 10
"""Positional-encoding frequencies of the normalised position (MVSNeRF: multires 10)."""
LAYERS, SKIP = 6, 4
"""Trunk layers (MVSNeRF: netdepth 6) and the layer after which the encoded position is fed again (skips [4])."""


def conv3d_bn_act(in_channels: int, out_channels: int, stride: int = 1) -> nn.Sequential:
    """3x3x3 conv (no bias) + BatchNorm3d + LeakyReLU(0.01): ``ConvBnReLU3D`` with InPlaceABN unrolled."""
    return nn.Sequential(nn.Conv3d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
                         nn.BatchNorm3d(out_channels), nn.LeakyReLU(0.01))


def up3d_bn_act(in_channels: int, out_channels: int) -> nn.Sequential:
    """Transposed 3x3x3 conv doubling every side + BatchNorm3d + LeakyReLU(0.01)."""
    return nn.Sequential(nn.ConvTranspose3d(in_channels, out_channels, 3, stride=2, padding=1, output_padding=1,
                                            bias=False),
                         nn.BatchNorm3d(out_channels), nn.LeakyReLU(0.01))


class CostRegNet(nn.Module):
    """``[1, in_channels, D, h, w]`` cost volume -> ``[1, 8, D, h, w]`` encoding volume (D, h, w multiples of 8).

    in -> 8, then 8 -> 16 -> 32 -> 64 with stride 2 (each followed by a same-width conv), then transposed convs back
    64 -> 32 -> 16 -> 8, each summed with the level's skip; no probability head.
    """

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        self.conv0 = conv3d_bn_act(in_channels, 8)
        self.conv1, self.conv2 = conv3d_bn_act(8, 16, 2), conv3d_bn_act(16, 16)
        self.conv3, self.conv4 = conv3d_bn_act(16, 32, 2), conv3d_bn_act(32, 32)
        self.conv5, self.conv6 = conv3d_bn_act(32, 64, 2), conv3d_bn_act(64, 64)
        self.conv7, self.conv9 = up3d_bn_act(64, 32), up3d_bn_act(32, 16)
        self.conv11 = up3d_bn_act(16, ENCODING_CHANNELS)

    def forward(self, volume: Tensor) -> Tensor:
        conv0 = self.conv0(volume)
        conv2 = self.conv2(self.conv1(conv0))
        conv4 = self.conv4(self.conv3(conv2))
        x = self.conv6(self.conv5(conv4))
        x = conv4 + self.conv7(x)
        x = conv2 + self.conv9(x)
        return conv0 + self.conv11(x)


def positional_encoding(x: Tensor, frequencies: int = FREQUENCIES) -> Tensor:
    """``[..., 3]`` -> ``[..., 3 + 6 * frequencies]``: x, then sin and cos of x at 2^0 .. 2^(F-1) (NeRF's)."""
    bands = 2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)
    scaled = (x[..., None, :] * bands[:, None]).flatten(-2)
    return torch.cat([x, scaled.sin(), scaled.cos()], dim=-1)


def _kaiming(layer: nn.Linear) -> nn.Linear:
    """MVSNeRF's ``weights_init``: Kaiming-normal weights, zero bias."""
    nn.init.kaiming_normal_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class ModulatedMLP(nn.Module):
    """MVSNeRF's renderer MLP with a semantic branch on its trunk.

    Each trunk layer is ``relu(Linear(h) * B(feature))`` with one ``B = Linear(feature -> width)`` for all layers (the
    per-sample feature modulates every layer, it is never concatenated); the encoded position is the first input and is
    concatenated again after layer ``SKIP``. Density ``relu(Linear(h))``; colour
    ``sigmoid(Linear(relu(Linear([Linear(h), direction]))))`` through ``width / 2``; class scores
    ``Linear(relu(Linear(h)))`` through ``width / 2`` (the semantic branch, before the view-dependent one).

    Args:
        feature_dim: per-sample feature channels (8 volume channels + 4 per view).
        width: trunk width.
        num_classes: K scores per sample (0: no semantic branch).
    """

    def __init__(self, feature_dim: int, width: int, num_classes: int) -> None:
        super().__init__()
        position = 3 + 6 * FREQUENCIES
        self.pts_linears = nn.ModuleList(
            [_kaiming(nn.Linear(position, width))]
            + [_kaiming(nn.Linear(width + (position if i == SKIP else 0), width)) for i in range(LAYERS - 1)]
        )
        self.pts_bias = nn.Linear(feature_dim, width)
        self.alpha_linear = _kaiming(nn.Linear(width, 1))
        self.feature_linear = _kaiming(nn.Linear(width, width))
        self.views_linear = _kaiming(nn.Linear(width + 3, width // 2))
        self.rgb_linear = _kaiming(nn.Linear(width // 2, 3))
        self.semantic = (nn.Sequential(nn.Linear(width, width // 2), nn.ReLU(), nn.Linear(width // 2, num_classes))
                         if num_classes else None)

    def forward(self, position: Tensor, feature: Tensor, direction: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Per sample: encoded position ``[N, 63]``, feature ``[N, feature_dim]``, unit direction in the reference
        camera's frame ``[N, 3]`` -> density ``[N]`` (>= 0, per unit step), colour ``[N, 3]`` in (0, 1) and the trunk's
        output ``[N, width]`` (the semantic branch's input, ``scores``)."""
        modulation = self.pts_bias(feature)
        h = position
        for index, layer in enumerate(self.pts_linears):
            h = F.relu(layer(h) * modulation)
            if index == SKIP:
                h = torch.cat([position, h], dim=-1)
        density = F.relu(self.alpha_linear(h))[:, 0]
        colour = F.relu(self.views_linear(torch.cat([self.feature_linear(h), direction], dim=-1)))
        return density, torch.sigmoid(self.rgb_linear(colour)), h

    def scores(self, trunk: Tensor) -> Tensor:
        """``[N, K]`` class scores of the trunk's output ``[N, width]``."""
        if self.semantic is None:
            raise RuntimeError("this MLP has no semantic branch")
        return self.semantic(trunk)
