"""NeRF's per-scene field, shared by the per-scene families (Semantic-NeRF, DM-NeRF): the positional encoding, the
MLP (trunk with a skip, raw density, view-dependent colour, a family's own branch on the trunk features) and the
weights of its densities along a ray."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import compositing_weights, density_opacity


def positional_encoding(x: Tensor, octaves: int) -> Tensor:
    """NeRF's encoding ``[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)]``: ``[..., 3]`` ->
    ``[..., 3 (1 + 2L)]``."""
    parts = [x]
    for octave in range(octaves):
        parts += [torch.sin(x * 2.0**octave), torch.cos(x * 2.0**octave)]
    return torch.cat(parts, -1)


class NeRFField(nn.Module):
    """The MLP of one pass: encoded position -> raw density, a branch's outputs (on the trunk features, detached with
    ``detach_branch`` so the branch's loss never shapes the geometry: DM-NeRF's object field) and, with the encoded
    view direction, colour.

    Args:
        width, depth, skip: the trunk: ``depth`` ReLU layers of ``width``, the encoded position concatenated after
            layer ``skip`` (0-based; NeRF's 4).
        position_dim, direction_dim: the encodings' channels.
        branch: a module from ``[N, width]`` trunk features, or None.
        detach_branch: the branch reads the trunk features detached.
    """

    def __init__(self, *, width: int, depth: int, skip: int, position_dim: int, direction_dim: int,
                 branch: nn.Module | None = None, detach_branch: bool = False) -> None:
        super().__init__()
        self.skip, self.detach_branch = skip, detach_branch
        self.trunk = nn.ModuleList(
            [nn.Linear(position_dim, width)]
            + [nn.Linear(width + (position_dim if i == skip + 1 else 0), width) for i in range(1, depth)])
        self.density = nn.Linear(width, 1)
        self.branch = branch
        self.feature = nn.Linear(width, width)
        self.colour = nn.Sequential(nn.Linear(width + direction_dim, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def forward(self, position: Tensor, direction: Tensor, with_branch: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        """``[N, P]`` encoded positions and ``[N, D]`` encoded directions -> raw density ``[N]``, colour ``[N, 3]`` in
        [0, 1] and the branch's output (None unless ``with_branch``)."""
        h = position
        for index, layer in enumerate(self.trunk):
            h = F.relu(layer(h))
            if index == self.skip:
                h = torch.cat([position, h], -1)
        colour = torch.sigmoid(self.colour(torch.cat([self.feature(h), direction], -1)))
        out = None
        if with_branch and self.branch is not None:
            out = self.branch(h.detach() if self.detach_branch else h)
        return self.density(h)[..., 0], colour, out


def check_field_options(**options: float) -> None:
    """One ConfigError naming every out-of-range option of a per-scene field (``model.<key>=<value>: expected ...``)."""
    from gpnerf_core import ConfigError

    depth = options["depth"]
    rules = {
        "coarse_samples": (lambda v: v >= 2, ">= 2"),
        "fine_samples": (lambda v: v >= 0, ">= 0"),
        "width": (lambda v: v >= 2 and v % 2 == 0, "an even number >= 2"),
        "depth": (lambda v: v >= 2, ">= 2"),
        "skip": (lambda v: 0 <= v < depth - 1, f"in [0, model.depth - 1) = [0, {depth - 1})"),
        "position_scale": (lambda v: v > 0, "> 0"),
        "position_frequencies": (lambda v: v >= 0, ">= 0"),
        "direction_frequencies": (lambda v: v >= 0, ">= 0"),
        "density_noise": (lambda v: v >= 0, ">= 0"),
    }
    problems = [f"model.{key}={value}: expected {rules[key][1]}" for key, value in options.items()
                if key in rules and not rules[key][0](value)]
    if problems:
        raise ConfigError("; ".join(problems))


def encoded_inputs(samples_points: Tensor, directions: Tensor, count: int, position_scale: float,
                   position_frequencies: int, direction_frequencies: int) -> tuple[Tensor, Tensor, Tensor]:
    """The encoded positions ``[R * S, P]`` (scaled by ``position_scale``), each sample's encoded unit direction
    ``[R * S, D]`` and the rays' lengths per unit of depth ``[R]`` (``|d|``: depth here is camera z)."""
    norms = directions.norm(dim=-1)
    position = positional_encoding(samples_points.reshape(-1, 3) * position_scale, position_frequencies)
    direction = positional_encoding(directions / norms[:, None], direction_frequencies)
    direction = direction[:, None].expand(-1, count, -1).reshape(-1, direction.shape[-1])
    return position, direction, norms


def density_weights(raw: Tensor, depths: Tensor, norms: Tensor, noise: float,
                    generator: torch.Generator | None) -> Tensor:
    """NeRF's ``raw2outputs`` weights ``[R, S]``: ``alpha = 1 - exp(-ReLU(raw + noise) * delta * |d|)``, the last
    interval 1e10; Gaussian noise of std ``noise`` on the raw density only with a ``generator`` (training)."""
    if generator is not None and noise > 0:
        raw = raw + noise * torch.randn(raw.shape, generator=generator, device=raw.device, dtype=raw.dtype)
    return compositing_weights(density_opacity(F.relu(raw) * norms[:, None], depths))
