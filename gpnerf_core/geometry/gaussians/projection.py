"""EWA projection of 3D Gaussians into one pinhole view (Zwicker et al. 2001, as 3DGS's ``computeCov2D``), in torch.

A Gaussian's covariance is ``Sigma = R S S^T R^T`` (R from its normalised quaternion, S = diag(scales)); its image is
the 2D Gaussian at the projected centre with covariance ``Sigma' = J W Sigma W^T J^T + 0.3 I``: W the world-to-camera
rotation, J the Jacobian of the pinhole projection at the centre, with x/z and y/z clamped to 1.3 times the half field
of view as the official rasterizer does (so a centre far outside the image does not blow the footprint up), and 0.3 px^2
on the diagonal (the low-pass filter). The conic is ``Sigma'^-1``. Vectorised over Gaussians, differentiable by
autograd in every input.

Where a Gaussian can be seen: a pixel gets ``alpha = min(0.99, o exp(-d^T conic d / 2))`` and skips it below 1/255, so
only pixels with ``d^T conic d <= k^2``, ``k = sqrt(2 ln(255 o))``, can see it: an ellipse whose bounding box has the
half-widths ``k sqrt(Sigma'_uu)`` and ``k sqrt(Sigma'_vv)`` (gsplat's opacity-aware box). Tiles are listed from that
box, so the rendering equals every Gaussian tested against every pixel, whatever the tile size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.geometry.gaussians.records import Gaussians
from gpnerf_core.runtime.finite import all_finite

LOW_PASS = 0.3
"""px^2 added to the 2D covariance's diagonal (the official low-pass filter)."""

JACOBIAN_LIMIT = 1.3
"""x/z and y/z are clamped to this many half fields of view inside J (the official rasterizer's 1.3)."""

ALPHA_MIN = 1.0 / 255.0
"""A Gaussian whose alpha at a pixel is below this is skipped there."""

ALPHA_MAX = 0.99
"""Alpha is capped here, so no single Gaussian is fully opaque."""

TRANSMITTANCE_MIN = 1e-4
"""A pixel stops at the first Gaussian that would bring its transmittance below this (that Gaussian excluded)."""

BOX_MARGIN = 1e-2
"""px added to the footprint box's half-widths, so rounding never drops a pixel the Gaussian reaches."""


def overflow_message(count: int, dtype: object) -> str:
    """The ``NonFiniteError`` both projections raise when ``count`` Gaussians' 2D covariances overflow ``dtype``."""
    return (f"rasterize_gaussians: scales: the 2D covariance of {count} Gaussian(s) overflows {dtype} in this view "
            f"(a Gaussian far larger than the image; scales are standard deviations in metres)")


@dataclass(frozen=True)
class ProjectedGaussians:
    """G Gaussians in one view's image.

    Attributes:
        means2d: ``[G, 2]`` centres ``(u, v)``, pixels (autograd graph).
        conics: ``[G, 3]`` ``(a, b, c)`` of the inverse 2D covariance ``[[a, b], [b, c]]``, 1/px^2 (autograd graph).
        depths: ``[G]`` camera z of the centres, metres (autograd graph; 1 for Gaussians behind the camera).
        opacities: ``[G]`` the Gaussians' opacities (autograd graph).
        extents: ``[G, 2]`` half-widths of the footprint box (u, v), pixels, detached.
        visible: ``[G]`` bool: in front of ``near``, opacity >= 1/255 and the box covers a pixel centre of the image.
        radii: ``[G]`` int32 ``ceil(3 sqrt(lambda_max))``, 0 where not visible.
        culled_behind, clamped: as ``Rasterized``'s.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    extents: Tensor
    visible: Tensor
    radii: Tensor
    culled_behind: int
    clamped: int


def rotation_matrices(quaternions: Tensor) -> Tensor:
    """``[G, 3, 3]`` rotations from ``[G, 4]`` quaternions ``(w, x, y, z)`` of any non-zero norm (normalised here)."""
    q = quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def project_gaussians(gaussians: Gaussians, intrinsics: Tensor, c2w: Tensor, height: int, width: int,
                      near: float) -> ProjectedGaussians:
    """Project ``gaussians`` into the view of ``intrinsics`` ``[3, 3]`` and ``c2w`` ``[4, 4]`` at ``height`` x ``width``
    (the module docstring states the maths); Gaussians at camera z <= ``near`` (metres) are culled."""
    means = gaussians.means
    kw = {"dtype": means.dtype, "device": means.device}
    intrinsics, c2w = intrinsics.to(**kw), c2w.to(**kw)
    rotation_cw = c2w[:3, :3].T
    camera = (means - c2w[:3, 3]) @ rotation_cw.T
    x, y, z = camera.unbind(-1)
    in_front = z > near
    z = torch.where(in_front, z, torch.ones_like(z))  # culled ones stay finite, so no NaN reaches a gradient
    fx, skew, cx = intrinsics[0, 0], intrinsics[0, 1], intrinsics[0, 2]
    fy, cy = intrinsics[1, 1], intrinsics[1, 2]
    means2d = torch.stack([(fx * x + skew * y) / z + cx, fy * y / z + cy], dim=-1)

    # J at the centre, x/z and y/z clamped to the field of view widened by 30 % on each side (the image edges are at
    # -0.5 and W - 0.5; for a centred principal point the limits are the official +-1.3 tan(fov / 2)).
    spare_x, spare_y = (JACOBIAN_LIMIT - 1) * 0.5 * width / fx, (JACOBIAN_LIMIT - 1) * 0.5 * height / fy
    tx = z * torch.clamp(x / z, min=-(cx + 0.5) / fx - spare_x, max=(width - 0.5 - cx) / fx + spare_x)
    ty = z * torch.clamp(y / z, min=-(cy + 0.5) / fy - spare_y, max=(height - 0.5 - cy) / fy + spare_y)
    zeros = torch.zeros_like(z)
    perspective = torch.stack([1 / z, zeros, -tx / (z * z), zeros, 1 / z, -ty / (z * z)], dim=-1).reshape(-1, 2, 3)
    jacobian = intrinsics[:2, :2] @ perspective  # [G, 2, 3]
    # Sigma' = A A^T with A = J W R S: PSD by construction; det(A A^T) = |A_0 x A_1|^2 >= 0 without cancellation.
    factor = jacobian @ rotation_cw @ rotation_matrices(gaussians.rotations) * gaussians.scales[:, None, :]
    row_u, row_v = factor.unbind(1)
    a, b, c = (row_u * row_u).sum(-1), (row_u * row_v).sum(-1), (row_v * row_v).sum(-1)
    det = torch.linalg.cross(row_u, row_v).pow(2).sum(-1)
    singular = in_front & (det <= 8 * torch.finfo(means.dtype).eps * (a + c) ** 2)
    det_filtered = det + LOW_PASS * (a + c) + LOW_PASS**2
    a, c = a + LOW_PASS, c + LOW_PASS
    conics = torch.stack([c / det_filtered, -b / det_filtered, a / det_filtered], dim=-1)
    sizes = torch.cat([conics, det_filtered[:, None]], dim=-1)
    if not all_finite(torch.where(in_front[:, None], sizes, torch.zeros_like(sizes))):
        overflowing = in_front & ~torch.isfinite(sizes).all(-1)
        raise NonFiniteError(overflow_message(int(overflowing.sum()), means.dtype))

    with torch.no_grad():
        opacities = gaussians.opacities.detach()
        reach = torch.sqrt(2 * torch.log((opacities / ALPHA_MIN).clamp_min(1.0)))  # k: 0 where never seen
        extents = reach[:, None] * torch.stack([a, c], dim=-1).detach().sqrt() + BOX_MARGIN
        centre = means2d.detach()
        low, high = torch.ceil(centre - extents), torch.floor(centre + extents)
        size = torch.tensor([width - 1, height - 1], dtype=means.dtype, device=means.device)
        visible = in_front & (opacities >= ALPHA_MIN) & ((low <= size) & (high >= 0) & (low <= high)).all(-1)
        spread = torch.sqrt(torch.clamp_min(((a - c) / 2) ** 2 + b**2, 0.1)).detach()  # official max(0.1, mid^2 - det)
        radii = torch.ceil(3 * torch.sqrt((a + c).detach() / 2 + spread)).clamp(max=2**30)
        radii = torch.where(visible, radii, torch.zeros_like(radii)).to(torch.int32)
    return ProjectedGaussians(
        means2d=means2d, conics=conics, depths=z, opacities=gaussians.opacities, extents=extents, visible=visible,
        radii=radii, culled_behind=int((~in_front).sum()), clamped=int(singular.sum()),
    )
