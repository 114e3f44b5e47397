"""A scene as 3D Gaussians in the world frame, as splat viewers and the standard 3D Gaussian splatting PLY hold it.

``GaussianScene`` is what a Gaussian family hands ``export`` (the PLY) and ``view`` (splats in the browser):
activated values in the world frame, colour as spherical harmonics whose directions are world directions, and a label
per Gaussian (its class or instance slot, -1 where the model has none).

The PLY is the one the official code writes (``GaussianModel.save_ply``) and common viewers read: one ``vertex``
element with float properties ``x y z nx ny nz``, ``f_dc_0..2`` (the degree-0 coefficient per channel),
``f_rest_*`` (the others, channel-major: all of red's, then green's, then blue's), ``opacity`` (a logit), ``scale_0..2``
(natural logs) and ``rot_0..3`` (``w x y z``), then an int ``label``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from gpnerf_core.geometry.gaussians.harmonics import sh_basis

OPACITY_LIMIT = 1e-6
"""Opacities are clamped to [this, 1 - this] before their logit is written (a 0 or 1 has no finite logit)."""


@dataclass(frozen=True)
class GaussianScene:
    """G Gaussians in the world frame.

    Attributes:
        means: ``[G, 3]`` metres; scales: ``[G, 3]`` standard deviations, metres; rotations: ``[G, 4]`` unit
            quaternions ``(w, x, y, z)``; opacities: ``[G]`` in [0, 1].
        harmonics: ``[G, 3, (degree + 1)^2]`` colour coefficients in world directions (``sh_colours``'s convention:
            colour = max(0, sum_k Y_k(d) c_k + 0.5)).
        labels: ``[G]`` int64 class id or instance slot, -1 where none.
        features: ``[G, C]`` what a family's decoder reads of each Gaussian (semantic features a head decodes, or K
            class scores), or None; not written to the PLY.
        feature_field: ``[G, C]`` each Gaussian's feature-field vector in a feature provider's channels (decoded where
            the model keeps them compressed: what a query by example or by embedding compares), or None; not written
            to the PLY.
    """

    means: Tensor
    scales: Tensor
    rotations: Tensor
    opacities: Tensor
    harmonics: Tensor
    labels: Tensor
    features: Tensor | None = None
    feature_field: Tensor | None = None

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    def subset(self, index: Tensor) -> "GaussianScene":
        """The Gaussians ``index`` picks (``[G]`` bool or ``[N]`` int64 rows), every column alike."""
        features = self.features[index] if self.features is not None else None
        field = self.feature_field[index] if self.feature_field is not None else None
        return GaussianScene(means=self.means[index], scales=self.scales[index], rotations=self.rotations[index],
                             opacities=self.opacities[index], harmonics=self.harmonics[index],
                             labels=self.labels[index], features=features, feature_field=field)

    def ply_columns(self) -> dict[str, np.ndarray]:
        """The standard 3DGS PLY's properties (the module docstring), then ``label``, as float32 / int32 arrays."""
        def column(values: Tensor) -> np.ndarray:
            return values.detach().to("cpu", torch.float32).numpy()

        columns: dict[str, np.ndarray] = {}
        for axis, name in enumerate("xyz"):
            columns[name] = column(self.means[:, axis])
        for name in ("nx", "ny", "nz"):
            columns[name] = np.zeros(self.count, dtype=np.float32)
        for channel in range(3):
            columns[f"f_dc_{channel}"] = column(self.harmonics[:, channel, 0])
        rest = self.harmonics[:, :, 1:].reshape(self.count, -1)  # channel-major
        for index in range(rest.shape[1]):
            columns[f"f_rest_{index}"] = column(rest[:, index])
        opacity = self.opacities.clamp(OPACITY_LIMIT, 1 - OPACITY_LIMIT)
        columns["opacity"] = column(torch.log(opacity / (1 - opacity)))
        for axis in range(3):
            columns[f"scale_{axis}"] = column(torch.log(self.scales[:, axis].clamp_min(1e-12)))
        rotations = self.rotations / self.rotations.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        for index in range(4):
            columns[f"rot_{index}"] = column(rotations[:, index])
        columns["label"] = self.labels.detach().to("cpu", torch.int32).numpy()
        return columns


SCENE_FIELDS = ("means", "scales", "rotations", "opacities", "harmonics", "labels")
"""``GaussianScene``'s columns, in the order ``scene_problem`` checks them."""


def scene_problem(scene: object, num_outputs: int | None = None) -> str | None:
    """What makes ``scene`` (a family's ``scene_gaussians``) unfit for ``export``'s PLY and ``view``'s splats, in one
    sentence naming the column, or None: not a ``GaussianScene``; a field that is not a tensor, has another row count
    than ``means`` or another trailing shape than the class documents (``harmonics`` ``[G, 3, (d + 1)^2]``); labels
    that are not integers, or outside -1 to ``num_outputs - 1`` (``semantic_output.num_outputs``; None: not checked).
    Finiteness is checked apart (``export``'s NaN message). The one rule of export and the contract kit."""
    if not isinstance(scene, GaussianScene):
        return f"scene_gaussians returned {type(scene).__name__}, expected a gpnerf_core.GaussianScene"
    trailing = {"means": (3,), "scales": (3,), "rotations": (4,), "opacities": (), "labels": ()}
    means = scene.means
    if not isinstance(means, Tensor) or means.dim() != 2:
        return f"its means is {_described(means)}, expected a [G, 3] tensor"
    count = int(means.shape[0])
    for name in SCENE_FIELDS:
        value = getattr(scene, name)
        if not isinstance(value, Tensor):
            return f"its {name} is {type(value).__name__}, expected a tensor with one row per Gaussian"
        if value.dim() == 0 or int(value.shape[0]) != count:
            return (f"its {name} has {int(value.shape[0]) if value.dim() else 0} rows for {count} means: every column "
                    "has one row per Gaussian")
        rest = tuple(value.shape[1:])
        if name == "harmonics":
            ok = len(rest) == 2 and rest[0] == 3 and math.isqrt(rest[1]) ** 2 == rest[1] and rest[1] >= 1
            if not ok:
                return f"its harmonics is {list(value.shape)}, expected [{count}, 3, (degree + 1)^2]"
        elif rest != trailing[name]:
            return f"its {name} is {list(value.shape)}, expected {[count, *trailing[name]]}"
    features = scene.features
    if features is not None and (not isinstance(features, Tensor) or features.dim() != 2
                                 or int(features.shape[0]) != count):
        return f"its features are {_described(features)}, expected None or a [{count}, C] tensor"
    labels = scene.labels
    if labels.is_floating_point() or labels.dtype == torch.bool:
        return f"its labels are {labels.dtype}, expected integers (int64: a class id or instance slot, -1 for none)"
    if num_outputs is not None and labels.numel():
        low, high = int(labels.min()), int(labels.max())
        if low < -1 or high >= num_outputs:
            return (f"its labels reach {low if low < -1 else high}; expected -1 (none) or an output of "
                    f"semantic_output (0 to {num_outputs - 1})")
    return None


def _described(value: object) -> str:
    return f"a tensor of shape {list(value.shape)}" if isinstance(value, Tensor) else type(value).__name__


def harmonics_rotation(rotation: Tensor, degree: int) -> Tensor:
    """``[(degree + 1)^2, (degree + 1)^2]`` M with ``Y(R^T d) = Y(d) M`` for every unit d: coefficients ``c`` of a colour
    defined on directions of a frame rotated by ``R`` (frame-to-world) are ``M c`` in world directions. Found by least
    squares on directions spread over the sphere (exact: each degree's harmonics span a rotation-invariant space, so
    M is block-diagonal and the fit has no residual)."""
    count = 2 * (degree + 1) ** 2 + 16
    index = torch.arange(count, dtype=torch.float64) + 0.5
    polar = torch.acos(1 - 2 * index / count)
    azimuth = math.pi * (1 + 5**0.5) * index  # a Fibonacci sphere
    directions = torch.stack([polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos()], dim=-1)
    world = sh_basis(directions, degree)
    framed = sh_basis(directions @ rotation.to(torch.float64), degree)  # Y(R^T d), d as rows
    return torch.linalg.lstsq(world, framed).solution.to(rotation.dtype)


def rotate_harmonics(coefficients: Tensor, rotations: Tensor, index: Tensor) -> Tensor:
    """``[G, C, k]`` coefficients defined in frames rotated by ``rotations[index]`` (``[F, 3, 3]`` frame-to-world, one
    per frame; ``index`` ``[G]``) turned into world directions."""
    degree = math.isqrt(coefficients.shape[-1]) - 1
    matrices = torch.stack([harmonics_rotation(r, degree) for r in rotations]).to(coefficients.dtype)  # [F, k, k]
    return torch.einsum("gkj,gcj->gck", matrices[index], coefficients)
