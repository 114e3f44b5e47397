"""The Gaussians of one scene as parameters whose row count changes while training (``GaussianField``).

Each per-Gaussian tensor is one parameter, one row per Gaussian, stored as 3DGS stores it (raw values activated when
rendered): centres, the degree-0 and higher spherical-harmonic colour coefficients, opacity logits, log scales,
quaternions, and the semantic feature. Beside them, buffers the checkpoint keeps so a resumed run trains exactly as an
uninterrupted one: the Gaussian ``count`` (checked against every tensor when weights are loaded), the scene's
``extent``, the colour's ``active_degree``, and the densification statistics (summed view-space gradient norms, how
often each Gaussian was seen, its largest footprint radius).
"""

from __future__ import annotations

from typing import Mapping

import torch
from torch import Tensor, nn

from gpnerf_core import DataError, Gaussians, resize_parameter, sh_coefficients

ROWS: dict[str, str] = {
    "means": "means",
    "harmonics_dc": "harmonics",
    "harmonics_rest": "harmonics_rest",
    "opacity_logits": "opacities",
    "log_scales": "scales",
    "rotations": "rotations",
    "features": "features",
}
"""Per-Gaussian parameter -> its learning-rate group (``model.lr.<group>``)."""
STATISTICS = ("gradient_sum", "gradient_count", "max_radius")
"""Per-Gaussian buffers of the densification statistics."""


class GaussianField(nn.Module):
    """G Gaussians of one scene (the module docstring); G = 0 until ``set_rows`` (initialisation) or weights load.

    Args:
        sh_degree: largest degree of the colour's spherical harmonics.
        feature_dim: F, channels of each Gaussian's semantic feature (0: none).
    """

    def __init__(self, sh_degree: int, feature_dim: int) -> None:
        super().__init__()
        self.sh_degree, self.feature_dim = int(sh_degree), int(feature_dim)
        for name, shape in self.row_shapes().items():
            setattr(self, name, nn.Parameter(torch.zeros(0, *shape)))
        self.register_buffer("count", torch.zeros((), dtype=torch.long))
        self.register_buffer("extent", torch.ones(()))
        self.register_buffer("active_degree", torch.zeros((), dtype=torch.long))
        for name in STATISTICS:
            self.register_buffer(name, torch.zeros(0))

    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        """Each per-Gaussian parameter's shape after its first dimension."""
        rest = sh_coefficients(self.sh_degree) - 1
        return {"means": (3,), "harmonics_dc": (3,), "harmonics_rest": (3, rest), "opacity_logits": (),
                "log_scales": (3,), "rotations": (4,), "features": (self.feature_dim,)}

    @property
    def size(self) -> int:
        """G."""
        return int(self.means.shape[0])

    def rows(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in ROWS}

    # ---- what is rendered -------------------------------------------------------------------------------------------

    def harmonics(self) -> Tensor:
        """``[G, 3, (active_degree + 1)^2]`` the colour coefficients in use."""
        used = sh_coefficients(int(self.active_degree))
        return torch.cat([self.harmonics_dc[..., None], self.harmonics_rest[..., : used - 1]], dim=-1)

    def activated(self, features: Tensor) -> Gaussians:
        """The rasterizer's ``Gaussians`` carrying ``features`` ``[G, C]``: scales ``exp``, opacities ``sigmoid``."""
        return Gaussians(self.means, self.log_scales.exp(), self.rotations, torch.sigmoid(self.opacity_logits),
                         features)

    # ---- changing the rows ------------------------------------------------------------------------------------------

    def set_rows(self, values: Mapping[str, Tensor], optimizer: torch.optim.Optimizer | None = None,
                 kept: Tensor | None = None) -> None:
        """Replace every per-Gaussian parameter by ``values`` (the same new row count for all), the optimizer's
        moments following the rows as ``gpnerf_core.resize_parameter`` says (``kept``: the old rows the first new ones
        continue; None with no optimizer). The statistics follow the same rows (new rows start at 0)."""
        sizes = {int(tensor.shape[0]) for tensor in values.values()}
        if set(values) != set(ROWS) or len(sizes) != 1:
            raise ValueError(f"GaussianField.set_rows: expected every one of {', '.join(ROWS)} with one row count, "
                             f"got {', '.join(f'{k} {list(v.shape)}' for k, v in values.items())}")
        count = sizes.pop()
        if kept is None and optimizer is not None:
            kept = torch.arange(self.size, device=self.means.device)
        for name, tensor in values.items():
            old = getattr(self, name)
            if optimizer is None:
                replacement = nn.Parameter(tensor.detach().clone().contiguous())
            else:
                replacement = resize_parameter(optimizer, old, tensor, kept)
            setattr(self, name, replacement)
        for name in STATISTICS:
            old = getattr(self, name)
            continued = old[kept] if kept is not None else old[:0]
            fresh = old.new_zeros(count - int(continued.shape[0]))
            setattr(self, name, torch.cat([continued, fresh]))
        self.count.fill_(count)

    def reset_statistics(self) -> None:
        for name in STATISTICS:
            getattr(self, name).zero_()

    def take_sizes(self, weights: Mapping[str, Tensor], prefix: str, source: str) -> None:
        """Give every per-Gaussian tensor the row count of ``weights`` (keys ``prefix`` + name) before they are loaded:
        a ``DataError`` naming ``source`` when the tensors disagree with each other or with the recorded count."""
        count_key = prefix + "count"
        if count_key not in weights:
            return  # not this family's weights: the loader names what is missing
        recorded = int(weights[count_key])
        for name in (*ROWS, *STATISTICS):
            key = prefix + name
            if key in weights and int(weights[key].shape[0]) != recorded:
                raise DataError(f"{source}: it records {recorded} Gaussians ({count_key}) but {key} has "
                                f"{int(weights[key].shape[0])} rows; the file is inconsistent (edited or written by "
                                "other code): use another checkpoint")
        device = self.means.device
        for name, shape in self.row_shapes().items():
            setattr(self, name, nn.Parameter(torch.zeros(recorded, *shape, device=device)))
        for name in STATISTICS:
            setattr(self, name, torch.zeros(recorded, device=device))
        self.count.fill_(recorded)
