"""Feature pyramid network over the encoder taps (GP-NeRF's semantic neck), in plain torch."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class FPN(nn.Module):
    """1x1 laterals, top-down nearest-upsample-and-add, one 3x3 output conv per level.

    No norm and no activation, so the outputs are signed; PyTorch's default init (GP-NeRF never applies the
    Xavier init its config names).

    Args:
        in_channels: channels of each input level, finest first.
        out_channels: channels of every output level.
    """

    def __init__(self, in_channels: list[int], out_channels: int) -> None:
        super().__init__()
        self.lateral_convs = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.fpn_convs = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, padding=1) for _ in in_channels)

    def forward(self, taps: list[Tensor]) -> list[Tensor]:
        """``taps[k]`` ``[N, in_channels[k], h_k, w_k]`` -> levels ``[N, out_channels, h_k, w_k]``, finest first."""
        laterals = [conv(x) for conv, x in zip(self.lateral_convs, taps)]
        for k in range(len(laterals) - 1, 0, -1):
            laterals[k - 1] = laterals[k - 1] + F.interpolate(
                laterals[k], size=laterals[k - 1].shape[-2:], mode="nearest"
            )
        return [conv(x) for conv, x in zip(self.fpn_convs, laterals)]


def concat_levels(levels: list[Tensor]) -> Tensor:
    """Upsample every level to the finest grid (bilinear, align_corners=True) and concatenate along channels.

    Returns ``[N, L * C, h_0, w_0]`` with level k in channels ``[k * C, (k + 1) * C)``.
    """
    size = levels[0].shape[-2:]
    resized = [levels[0]] + [F.interpolate(x, size=size, mode="bilinear", align_corners=True) for x in levels[1:]]
    return torch.cat(resized, dim=1)
