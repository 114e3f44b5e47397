"""The Gaussians of one scene as trainable parameters whose row count changes while training (``GaussianParameters``).

Each per-Gaussian tensor is one parameter, one row per Gaussian, stored as 3D Gaussian splatting stores it (raw values
activated when rendered; gsplat's ``splats`` dict): centres ``means``, the degree-0 and higher spherical-harmonic colour
coefficients ``harmonics_dc`` / ``harmonics_rest``, ``opacity_logits``, ``log_scales``, ``rotations`` (quaternions
``(w, x, y, z)``, any norm), and the family's own channels (a semantic feature, an identity encoding) named at
construction. A density strategy's per-Gaussian statistics are buffers beside them (``register_row_state``): the
checkpoint keeps them and they follow the rows whenever rows are added or removed. Beside those, buffers that make a
resumed run train exactly as an uninterrupted one: the Gaussian ``count`` (checked against every tensor when weights
are loaded), the scene's ``extent`` (metres: the scale densification and the centres' learning rate are relative to)
and the colour's ``active_degree``.
"""

from __future__ import annotations

import math
from typing import Mapping

import torch
from torch import Tensor, nn

from gpnerf_core.errors import DataError
from gpnerf_core.geometry.gaussians.harmonics import colour_to_dc, sh_coefficients
from gpnerf_core.geometry.gaussians.records import Gaussians
from gpnerf_core.geometry.gaussians.rows import resize_parameter
from gpnerf_core.geometry.gaussians.scene import GaussianScene

GEOMETRY_ROWS = ("means", "harmonics_dc", "harmonics_rest", "opacity_logits", "log_scales", "rotations")
"""The per-Gaussian parameters every ``GaussianParameters`` has, in their registration order."""


class GaussianParameters(nn.Module):
    """G Gaussians of one scene (the module docstring); G = 0 until ``set_rows`` (initialisation) or weights load.

    Args:
        sh_degree: largest degree of the colour's spherical harmonics (0 to 3).
        channels: the family's own per-Gaussian channels, ``name -> width`` (``{"features": 16}``); a width of 0 keeps
            an empty ``[G, 0]`` row.
    """

    def __init__(self, sh_degree: int, channels: Mapping[str, int] | None = None) -> None:
        super().__init__()
        self.sh_degree = int(sh_degree)
        self.channels = {str(name): int(width) for name, width in (channels or {}).items()}
        clash = [name for name in self.channels if name in GEOMETRY_ROWS or hasattr(nn.Module, name)]
        if clash:
            raise ValueError(f"GaussianParameters channel {clash[0]!r} clashes with a parameter it has already")
        for name, shape in self.row_shapes().items():
            setattr(self, name, nn.Parameter(torch.zeros(0, *shape)))
        self.register_buffer("count", torch.zeros((), dtype=torch.long))
        self.register_buffer("extent", torch.ones(()))
        self.register_buffer("active_degree", torch.zeros((), dtype=torch.long))
        self._row_state: list[str] = []

    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        """Each per-Gaussian parameter's shape after its first dimension."""
        rest = sh_coefficients(self.sh_degree) - 1
        geometry = {"means": (3,), "harmonics_dc": (3,), "harmonics_rest": (3, rest), "opacity_logits": (),
                    "log_scales": (3,), "rotations": (4,)}
        return geometry | {name: (width,) for name, width in self.channels.items()}

    @property
    def size(self) -> int:
        """G."""
        return int(self.means.shape[0])

    def rows(self) -> dict[str, nn.Parameter]:
        """Every per-Gaussian parameter by name, geometry first, then the family's channels."""
        return {name: getattr(self, name) for name in self.row_shapes()}

    def register_row_state(self, name: str) -> None:
        """A per-Gaussian float buffer ``name`` (a strategy's statistic), zero for every row, kept by checkpoints and
        following the rows (``set_rows``); registering it again keeps it."""
        if name in self._row_state:
            return
        if hasattr(self, name):
            raise ValueError(f"GaussianParameters row state {name!r} clashes with a member it has already")
        self.register_buffer(name, torch.zeros(self.size, device=self.means.device))
        self._row_state.append(name)

    def row_state(self) -> dict[str, Tensor]:
        """The registered per-Gaussian buffers by name (the strategies' ``state``; they write them in place)."""
        return {name: getattr(self, name) for name in self._row_state}

    # ---- what is rendered -------------------------------------------------------------------------------------------

    def harmonics(self) -> Tensor:
        """``[G, 3, (active_degree + 1)^2]`` the colour coefficients in use."""
        used = sh_coefficients(int(self.active_degree))
        return torch.cat([self.harmonics_dc[..., None], self.harmonics_rest[..., : used - 1]], dim=-1)

    def activated(self, features: Tensor) -> Gaussians:
        """The rasterizer's ``Gaussians`` carrying ``features`` ``[G, C]``: scales ``exp``, opacities ``sigmoid``."""
        return Gaussians(self.means, self.log_scales.exp(), self.rotations, torch.sigmoid(self.opacity_logits),
                         features)

    def as_scene(self, labels: Tensor | None = None) -> GaussianScene:
        """The Gaussians activated in the world frame (``export``'s PLY, the viewer's splats); ``labels`` ``[G]`` (-1 for
        none)."""
        if labels is None:
            labels = torch.full((self.size,), -1, dtype=torch.long, device=self.means.device)
        harmonics = torch.cat([self.harmonics_dc[..., None], self.harmonics_rest], dim=-1)
        rotations = self.rotations / self.rotations.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return GaussianScene(means=self.means, scales=self.log_scales.exp(), rotations=rotations,
                             opacities=torch.sigmoid(self.opacity_logits), harmonics=harmonics, labels=labels)

    # ---- changing the rows ------------------------------------------------------------------------------------------

    def set_rows(self, values: Mapping[str, Tensor], optimizer: torch.optim.Optimizer | None = None,
                 kept: Tensor | None = None) -> None:
        """Replace every per-Gaussian parameter by ``values`` (the same new row count for all), the optimizer's
        moments following the rows as ``gpnerf_core.resize_parameter`` says (``kept``: the old rows the first new ones
        continue; None with no optimizer). The row state follows the same rows (new rows start at 0)."""
        names = list(self.row_shapes())
        sizes = {int(tensor.shape[0]) for tensor in values.values()}
        if set(values) != set(names) or len(sizes) != 1:
            raise ValueError(f"GaussianParameters.set_rows: expected every one of {', '.join(names)} with one row "
                             f"count, got {', '.join(f'{k} {list(v.shape)}' for k, v in values.items())}")
        count = sizes.pop()
        if kept is None and optimizer is not None:
            kept = torch.arange(self.size, device=self.means.device)
        for name in names:
            old, tensor = getattr(self, name), values[name]
            if optimizer is None:
                replacement = nn.Parameter(tensor.detach().clone().contiguous())
            else:
                replacement = resize_parameter(optimizer, old, tensor, kept)
            setattr(self, name, replacement)
        for name in self._row_state:
            old = getattr(self, name)
            continued = old[kept] if kept is not None else old[:0]
            fresh = old.new_zeros(count - int(continued.shape[0]))
            setattr(self, name, torch.cat([continued, fresh]))
        self.count.fill_(count)

    def take_sizes(self, weights: Mapping[str, Tensor], prefix: str, source: str) -> None:
        """Give every per-Gaussian tensor the row count of ``weights`` (keys ``prefix`` + name) before they are loaded:
        a ``DataError`` naming ``source`` when the tensors disagree with each other or with the recorded count, or the
        recorded active degree is not one of ``sh_degree``'s."""
        count_key = prefix + "count"
        if count_key not in weights:
            return  # not these parameters' weights: the loader names what is missing
        recorded = int(weights[count_key])
        degree_key = prefix + "active_degree"
        if degree_key in weights:
            degree = weights[degree_key]
            if degree.numel() != 1 or not 0 <= float(degree) <= self.sh_degree or float(degree) != int(degree):
                raise DataError(f"{source}: {degree_key}={degree.tolist()!r}: expected the colour's active "
                                f"spherical-harmonic degree, an integer in [0, {self.sh_degree}] (model.sh_degree="
                                f"{self.sh_degree}); the file is inconsistent (edited or written by other code): use "
                                "another checkpoint")
        for name in (*self.row_shapes(), *self._row_state):
            key = prefix + name
            if key in weights and int(weights[key].shape[0]) != recorded:
                raise DataError(f"{source}: it records {recorded} Gaussians ({count_key}) but {key} has "
                                f"{int(weights[key].shape[0])} rows; the file is inconsistent (edited or written by "
                                "other code): use another checkpoint")
        device = self.means.device
        for name, shape in self.row_shapes().items():
            setattr(self, name, nn.Parameter(torch.zeros(recorded, *shape, device=device)))
        for name in self._row_state:
            setattr(self, name, torch.zeros(recorded, device=device))
        self.count.fill_(recorded)


def rows_from_points(xyz: Tensor, rgb: Tensor, scales: Tensor, *, sh_degree: int, opacity: float) -> dict[str, Tensor]:
    """3D Gaussian splatting's start from points (``create_from_pcd``): centres at the points ``[P, 3]``, colour
    ``rgb`` ``[P, 3]`` in [0, 1] as the degree-0 harmonic (higher degrees 0), isotropic ``scales`` ``[P]`` (metres,
    ``neighbour_scales``), no rotation, every opacity ``opacity`` in (0, 1). The geometry rows of
    ``GaussianParameters``; a family adds its own channels."""
    count = xyz.shape[0]
    rotations = torch.zeros(count, 4, dtype=xyz.dtype, device=xyz.device)
    rotations[:, 0] = 1.0
    rest = sh_coefficients(sh_degree) - 1
    return {
        "means": xyz,
        "harmonics_dc": colour_to_dc(rgb),
        "harmonics_rest": torch.zeros(count, 3, rest, dtype=xyz.dtype, device=xyz.device),
        "opacity_logits": torch.full((count,), math.log(opacity / (1 - opacity)), dtype=xyz.dtype, device=xyz.device),
        "log_scales": scales.log()[:, None].repeat(1, 3),
        "rotations": rotations,
    }


def rows_from_gaussians(scene: GaussianScene, *, sh_degree: int) -> dict[str, Tensor]:
    """The geometry rows of Gaussians another model made (a feed-forward family's ``scene_gaussians``): activated values
    turned back into stored ones (log scales, opacity logits), the colour's harmonics cut or padded with zeros to
    ``sh_degree``. A family adds its own channels (from ``scene.labels``, say)."""
    wanted = sh_coefficients(sh_degree)
    harmonics = scene.harmonics[..., :wanted]
    if harmonics.shape[-1] < wanted:
        harmonics = torch.cat([harmonics, harmonics.new_zeros(*harmonics.shape[:-1], wanted - harmonics.shape[-1])],
                              dim=-1)
    opacities = scene.opacities.clamp(1e-6, 1 - 1e-6)
    return {
        "means": scene.means,
        "harmonics_dc": harmonics[..., 0],
        "harmonics_rest": harmonics[..., 1:],
        "opacity_logits": torch.log(opacities / (1 - opacities)),
        "log_scales": scene.scales.clamp_min(1e-12).log(),
        "rotations": scene.rotations,
    }
