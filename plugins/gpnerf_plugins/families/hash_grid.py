"""A per-scene field on a multiresolution hash grid (Instant-NGP: Müller et al., SIGGRAPH 2022), the faster field of
the per-scene families (``model.field=grid``): the same inputs and outputs as ``NeRFField`` (raw density, colour from
the view direction, a family's branch), so the family's sampling, rendering and losses are unchanged.

- **Encoding**: ``levels`` grids, resolutions growing geometrically from ``base_resolution`` to ``finest_resolution``
  cells per unit of the scaled position (the family's ``position_scale`` x world units: 0.1 x metres by default, so
  16..1024 cells per unit are cells of 62 cm down to 1 cm); each level's cell corners are hashed (Instant-NGP's
  ``x * 1 ^ y * 2654435761 ^ z * 805459861`` modulo its table of ``2^table_log2`` entries of ``features`` values) and
  trilinearly interpolated. Every level is hashed, the coarse ones too: the field needs no scene bounds (a corner of a
  coarse level that no sample reaches never takes a table entry's gradient).
- **Networks** (Instant-NGP's NeRF sizes): density ``Linear(L F, width)``, ReLU, ``Linear(width, 16)``, the first
  output the raw density and the other 15 the geometry features; colour ``Linear(15 + D, width)``, ReLU,
  ``Linear(width, width)``, ReLU, ``Linear(width, 3)``, sigmoid, on the geometry features and the encoded direction;
  the family's branch (Semantic-NeRF's semantic head) on the density network's hidden ``width`` features.

What differs from Instant-NGP, to keep the family's outputs: the density stays the family's ``ReLU(raw)`` with its
training noise (Instant-NGP: ``exp``), the direction keeps the family's positional encoding (Instant-NGP: spherical
harmonics), the samples stay the family's coarse and fine passes (Instant-NGP: an occupancy grid marching the rays),
and the tables are dense parameters updated by the trainer's Adam (Instant-NGP skips entries without gradient).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

HASH_PRIMES = (1, 2654435761, 805459861)
"""Instant-NGP's per-axis primes of the spatial hash."""
GEOMETRY_FEATURES = 15
"""Outputs of the density network besides the raw density, read by the colour network (Instant-NGP's 15)."""


class _WeightedLookup(torch.autograd.Function):
    """``sum_c weights[..., c] x table[index[..., c]]``: ``[M, C]`` indices and weights -> ``[M, F]``. Its backward
    accumulates the table's gradient with ``torch.bincount`` (about 7x faster on CPU than ``F.embedding``'s backward
    or ``index_add_`` for these sizes); the weights take no gradient (the sample positions are not optimised)."""

    @staticmethod
    def forward(ctx, table: Tensor, index: Tensor, weights: Tensor) -> Tensor:
        ctx.save_for_backward(index, weights)
        ctx.table_shape = table.shape
        values = table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[1])
        return torch.einsum("mc,mcf->mf", weights, values)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, None, None]:
        index, weights = ctx.saved_tensors
        rows, features = ctx.table_shape
        per_value = weights[..., None] * grad[:, None, :]  # [M, C, F]
        flat = (index[..., None] * features + torch.arange(features, device=index.device)).reshape(-1)
        summed = torch.bincount(flat, weights=per_value.reshape(-1), minlength=rows * features)
        return summed.view(rows, features).to(grad.dtype), None, None


class HashGridEncoding(nn.Module):
    """Instant-NGP's multiresolution hash encoding: ``[N, 3]`` positions -> ``[N, levels x features]``.

    Args:
        levels: L grids.
        features: values per table entry (F).
        table_log2: each level's table holds ``2^table_log2`` entries.
        base_resolution, finest_resolution: cells per unit of the coarsest and the finest level (the levels between
            grow by one factor, ``floor(base x growth^l)``).
    """

    def __init__(self, *, levels: int, features: int, table_log2: int, base_resolution: float,
                 finest_resolution: float) -> None:
        super().__init__()
        self.levels, self.features, self.table_size = int(levels), int(features), 2 ** int(table_log2)
        growth = (finest_resolution / base_resolution) ** (1.0 / (levels - 1)) if levels > 1 else 1.0
        # floor(N_min b^l) (Instant-NGP's eq. 2); the epsilon keeps b^(L-1) x N_min = N_max from rounding down
        resolutions = [math.floor(base_resolution * growth**level + 1e-6) for level in range(levels)]
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        self.register_buffer("offsets", torch.arange(levels, dtype=torch.int32) * self.table_size, persistent=False)
        self.register_buffer("primes", torch.tensor(HASH_PRIMES, dtype=torch.int64), persistent=False)
        # Instant-NGP's initialisation: uniform in +-1e-4, so the untrained field starts near a constant
        self.tables = nn.Parameter(torch.empty(levels * self.table_size, features).uniform_(-1e-4, 1e-4))

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def forward(self, positions: Tensor) -> Tensor:
        """``[N, 3]`` positions (scaled units) -> ``[N, L x F]``, level-major."""
        count = positions.shape[0]
        scaled = positions.to(self.resolutions.dtype)[None] * self.resolutions[:, None, None]  # [L, N, 3]
        lower = torch.floor(scaled)
        fraction = scaled - lower
        # per axis, the lower and upper corner's hash term and weight: [L, N, 3, 2]. The table index keeps the low
        # table_log2 bits of the xor, which are the xor of each term's low bits: masked first, they fit int32
        corner = lower.to(torch.int64)[..., None] + torch.tensor([0, 1], device=positions.device)
        term = ((corner * self.primes[:, None]) & (self.table_size - 1)).to(torch.int32)
        weight = torch.stack([1 - fraction, fraction], -1)
        x, y, z = (term[:, :, axis] for axis in range(3))
        index = x[..., :, None, None] ^ y[..., None, :, None] ^ z[..., None, None, :]
        wx, wy, wz = (weight[:, :, axis] for axis in range(3))
        weights = wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]  # [L, N, 2, 2, 2]
        index = (index + self.offsets[:, None, None, None, None]).reshape(-1, 8)
        encoded = _WeightedLookup.apply(self.tables, index, weights.reshape(-1, 8).to(self.tables.dtype))
        return encoded.view(self.levels, count, self.features).transpose(0, 1).reshape(count, self.out_dim)


class HashGridField(nn.Module):
    """One pass's field on a hash grid, called as ``NeRFField`` is: scaled positions ``[N, 3]`` and encoded directions
    ``[N, D]`` -> raw density ``[N]``, colour ``[N, 3]`` in [0, 1] and the branch's output (module docstring).

    Args:
        levels, features, table_log2, base_resolution, finest_resolution: the encoding's (``HashGridEncoding``).
        width: hidden width of the density and colour networks (Instant-NGP: 64).
        direction_dim: the encoded direction's channels.
        branch: a module from ``[N, width]`` hidden density features, or None.
        detach_branch: the branch reads those features detached.
    """

    def __init__(self, *, levels: int, features: int, table_log2: int, base_resolution: float,
                 finest_resolution: float, width: int, direction_dim: int, branch: nn.Module | None = None,
                 detach_branch: bool = False) -> None:
        super().__init__()
        self.encoding = HashGridEncoding(levels=levels, features=features, table_log2=table_log2,
                                         base_resolution=base_resolution, finest_resolution=finest_resolution)
        self.hidden = nn.Linear(self.encoding.out_dim, width)
        self.density = nn.Linear(width, 1 + GEOMETRY_FEATURES)
        self.colour = nn.Sequential(nn.Linear(GEOMETRY_FEATURES + direction_dim, width), nn.ReLU(),
                                    nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 3))
        self.branch, self.detach_branch = branch, detach_branch

    def grid_parameters(self) -> list[nn.Parameter]:
        """The hash tables (trained at ``model.lr.grid``; the networks at ``model.lr.field``)."""
        return [self.encoding.tables]

    def forward(self, position: Tensor, direction: Tensor, with_branch: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        h = F.relu(self.hidden(self.encoding(position)))
        density = self.density(h)
        colour = torch.sigmoid(self.colour(torch.cat([density[:, 1:], direction], -1)))
        out = None
        if with_branch and self.branch is not None:
            out = self.branch(h.detach() if self.detach_branch else h)
        return density[:, 0], colour, out
