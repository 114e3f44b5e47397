"""View-dependent colour of 3D Gaussians from real spherical harmonics, and the quaternions of camera rotations.

3DGS stores a Gaussian's colour as spherical-harmonic coefficients per channel (degree up to 3 there, 4 in MVSplat:
``(degree + 1)^2`` coefficients) and evaluates them in the direction from the camera centre to the Gaussian; the
official rasterizer then adds 0.5 and clamps at 0 (``computeColorFromSH``). The rasterizer here composites colours a
caller has evaluated already, so a family calls ``sh_colours`` per view. The constants and the order of the basis are
the official ``sh_utils.eval_sh``'s (x, y, z of a unit direction).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)
SH_C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892, 0.10578554691520431,
         -0.6690465435572892, 0.47308734787878004, -1.7701307697799304, 0.6258357354491761)
MAX_DEGREE = 4


def sh_coefficients(degree: int) -> int:
    """``(degree + 1)^2``: coefficients per channel of harmonics up to ``degree`` (0 to 4)."""
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= MAX_DEGREE:
        raise ConfigError(f"spherical-harmonic degree {degree!r}: expected an integer in [0, {MAX_DEGREE}]")
    return (degree + 1) ** 2


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """``[N, (degree + 1)^2]`` the real spherical harmonics at unit ``directions`` ``[N, 3]`` (the official order)."""
    sh_coefficients(degree)
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, SH_C0)]
    if degree > 0:
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        terms += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree > 2:
        terms += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                  SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    if degree > 3:
        terms += [SH_C4[0] * xy * (xx - yy), SH_C4[1] * yz * (3 * xx - yy), SH_C4[2] * xy * (7 * zz - 1),
                  SH_C4[3] * yz * (7 * zz - 3), SH_C4[4] * (zz * (35 * zz - 30) + 3), SH_C4[5] * xz * (7 * zz - 3),
                  SH_C4[6] * (xx - yy) * (7 * zz - 1), SH_C4[7] * xz * (xx - 3 * yy),
                  SH_C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))]
    return torch.stack(terms, dim=-1)


def sh_colours(coefficients: Tensor, directions: Tensor) -> Tensor:
    """``[N, C]`` colours ``max(0, sum_k Y_k(d) c_k + 0.5)`` of harmonics ``coefficients`` ``[N, C, (degree + 1)^2]``
    seen along ``directions`` ``[N, 3]`` (any non-zero length: normalised here), as the official rasterizer."""
    count = coefficients.shape[-1]
    degree = math.isqrt(count) - 1
    if (degree + 1) ** 2 != count:
        raise ConfigError(f"{count} spherical-harmonic coefficients per channel: expected (degree + 1)^2")
    unit = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(unit, degree).to(coefficients.dtype)
    return (torch.einsum("nck,nk->nc", coefficients, basis) + 0.5).clamp_min(0.0)


def colour_to_dc(colours: Tensor) -> Tensor:
    """The degree-0 coefficient that ``sh_colours`` turns into ``colours`` (3DGS's ``RGB2SH``): ``(c - 0.5) / C0``."""
    return (colours - 0.5) / SH_C0


def quaternions_of(rotations: Tensor) -> Tensor:
    """``[N, 4]`` unit quaternions ``(w, x, y, z)`` of rotation matrices ``[N, 3, 3]`` (Shepperd's method: the largest
    of the four squared components is taken first, so no branch divides by a small number); ``w >= 0``."""
    m = rotations
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    squares = torch.stack([1 + trace, 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                           1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], 1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1)
    largest = squares.argmax(dim=-1)
    s = torch.sqrt(squares.gather(1, largest[:, None]).clamp_min(1e-12))[:, 0] * 2  # 4 |q_largest|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s21, s02, s10 = m[:, 2, 1] + m[:, 1, 2], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 0] + m[:, 0, 1]
    candidates = torch.stack([
        torch.stack([s / 4, d21 / s, d02 / s, d10 / s], -1),
        torch.stack([d21 / s, s / 4, s10 / s, s02 / s], -1),
        torch.stack([d02 / s, s10 / s, s / 4, s21 / s], -1),
        torch.stack([d10 / s, s02 / s, s21 / s, s / 4], -1),
    ], dim=1)  # [N, 4 cases, 4]
    q = candidates.gather(1, largest[:, None, None].expand(-1, 1, 4))[:, 0]
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0).to(q.dtype)
    return q / q.norm(dim=-1, keepdim=True)


def quaternion_product(left: Tensor, right: Tensor) -> Tensor:
    """``[N, 4]`` Hamilton products ``left * right`` of ``(w, x, y, z)`` quaternions (broadcasting): the rotation
    ``right`` followed by ``left``."""
    w1, x1, y1, z1 = left.unbind(-1)
    w2, x2, y2, z2 = right.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], dim=-1)
