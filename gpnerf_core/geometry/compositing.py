"""Volume rendering along a ray: opacities from densities, compositing weights, and what they composite.

Shared by every family that renders by density (NeRF's quadrature, Max 1995): a sample's weight is its opacity times
the transmittance of the samples before it, ``w_i = alpha_i * prod_{j<i} (1 - alpha_j)``; the colour, depth, features
or class scores of a ray are the weighted sums of its samples' (label rendering: per-sample scores composited so).
"""

from __future__ import annotations

import torch
from torch import Tensor

FAR_INTERVAL = 1e10
"""The last sample's interval (NeRF's): it absorbs whatever density is left at the far end of the ray."""


def density_opacity(density: Tensor, depths: Tensor | None = None) -> Tensor:
    """``alpha = 1 - exp(-sigma * delta)`` ``[R, S]`` from non-negative densities ``[R, S]``.

    Args:
        depths: ``[R, S]`` sample depths, ascending: ``delta`` is the gap to the next sample (``FAR_INTERVAL`` after the
            last). None: ``delta = 1`` for every sample, as Semantic-Ray, NeuRay and MVSNeRF's code do (their densities
            absorb the interval).
    """
    if depths is None:
        return 1.0 - torch.exp(-density)
    intervals = torch.cat([depths[:, 1:] - depths[:, :-1], torch.full_like(depths[:, :1], FAR_INTERVAL)], dim=-1)
    return 1.0 - torch.exp(-density * intervals)


def compositing_weights(opacity: Tensor) -> Tensor:
    """``w_i = alpha_i * prod_{j<i} (1 - alpha_j)`` ``[R, S]`` from opacities in [0, 1] ``[R, S]``; each ray's weights sum
    to at most 1 (the rest passes through the far end)."""
    transmittance = torch.cumprod(1.0 - opacity + 1e-10, dim=-1)
    transmittance = torch.cat([torch.ones_like(opacity[:, :1]), transmittance[:, :-1]], dim=-1)
    return opacity * transmittance


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """``sum_s w[r, s] * values[r, s, c]``: ``[R, S]`` x ``[R, S, C]`` -> ``[R, C]``."""
    return torch.einsum("rs,rsc->rc", weights, values)
