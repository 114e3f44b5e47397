"""``rasterize_gaussians``: project, bin into tiles, composite front to back with the chosen backend.

Per pixel, front to back over its tile's depth-sorted list (the official 3DGS kernel's rules): ``power = -d^T conic d
/ 2`` with d the centre minus the pixel centre, skipped if ``power > 0``; ``alpha = min(0.99, o exp(power))``, skipped
below 1/255; the walk stops at the first Gaussian that would bring the transmittance T under 1e-4, that one excluded;
otherwise ``w = alpha T`` weighs its features and depth and ``T <- T (1 - alpha)``. ``alpha_out = 1 - T``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import fields
from typing import Callable

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError, NonFiniteError
from gpnerf_core.geometry.gaussians.binning import TileBins, bin_gaussians, fill_tiles
from gpnerf_core.geometry.gaussians.gsplat_backend import composite_gsplat, gsplat_available
from gpnerf_core.geometry.gaussians.numba_backend import (
    composite_numba, fill_tiles_numba, kernels, project_and_bin_numba,
)
from gpnerf_core.geometry.gaussians.projection import project_gaussians
from gpnerf_core.geometry.gaussians.records import Gaussians, Rasterized
from gpnerf_core.geometry.gaussians.torch_backend import composite_torch
from gpnerf_core.runtime.finite import all_finite
from gpnerf_core.types import TargetCamera

Compositor = Callable[[Tensor, Tensor, Tensor, Tensor, Tensor, TileBins, int, int], tuple[Tensor, Tensor, Tensor]]

BACKENDS: dict[str, Compositor] = {"torch": composite_torch, "numba": composite_numba, "gsplat": composite_gsplat}
"""Backend name -> compositor; ``"auto"`` picks one of them (``choose_backend``)."""

RASTERIZER_BACKENDS: tuple[str, ...] = ("auto", *BACKENDS)
"""The names ``rasterize_gaussians(backend=...)`` takes."""

NEAR_CULL = 0.2
"""Metres: Gaussians at camera z <= this are culled by default, as the official 3DGS rasterizer's ``in_frustum``
(``p_view.z <= 0.2``); 0.01 before issue 55."""


def choose_backend(name: str, device: torch.device) -> str:
    """The backend ``name`` resolves to for tensors on ``device``: ``"auto"`` is gsplat on CUDA when installed, numba on
    the CPU when importable, else torch; a named backend that cannot run there is a ``ConfigError``."""
    if name == "auto":
        if device.type == "cuda" and gsplat_available():
            return "gsplat"
        return "numba" if device.type == "cpu" and kernels() is not None else "torch"
    if name not in BACKENDS:
        raise ConfigError(f"rasterizer backend {name!r} is unknown; known: auto, {', '.join(BACKENDS)}")
    if name == "numba" and (device.type != "cpu" or kernels() is None):
        raise ConfigError(f"rasterizer backend 'numba' needs CPU tensors and an importable numba "
                          f"(tensors on {device}, numba {'importable' if kernels() else 'not importable'})")
    if name == "gsplat" and (device.type != "cuda" or not gsplat_available()):
        raise ConfigError(f"rasterizer backend 'gsplat' needs CUDA tensors and gsplat installed "
                          f"(tensors on {device}, gsplat {'installed' if gsplat_available() else 'not installed'})")
    return name


def _needs_gradient(gaussians: Gaussians, intrinsics: Tensor, c2w: Tensor) -> bool:
    """Autograd records this call: the projection must then be torch's (the numba one is for rendering only)."""
    tensors = (*(getattr(gaussians, field.name) for field in fields(Gaussians)), intrinsics, c2w)
    return torch.is_grad_enabled() and any(tensor.requires_grad for tensor in tensors)


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _extremes(name: str, tensor: Tensor) -> tuple[float, float]:
    """``tensor``'s min and max in one ``aminmax`` pass; NaN or Inf is a ``NonFiniteError`` naming ``name``."""
    values = tensor.detach()
    if values.numel() == 0:
        return 0.0, 0.0
    if not values.is_floating_point():
        values = values.double()
    low, high = torch.aminmax(values)
    low, high = float(low), float(high)
    if not (math.isfinite(low) and math.isfinite(high)):
        raise NonFiniteError(f"rasterize_gaussians: {name} holds NaN or Inf")
    return low, high


def _check(gaussians: Gaussians, intrinsics: Tensor, c2w: Tensor, height: int, width: int, near: float,
           tile_size: int, background: Tensor | None) -> None:
    """Every argument against what the docstring expects (docs/rasterizer.md's table of checks), before any kernel."""
    for name, value in (("height", height), ("width", width), ("tile_size", tile_size)):
        if not _is_integer(value):
            raise ConfigError(f"rasterize_gaussians: {name}={value!r} ({type(value).__name__}): expected an int "
                              f"(pixels)")
    if min(height, width, tile_size) < 1:
        raise ConfigError(f"rasterizer image {height} x {width}, tile_size {tile_size}: expected all >= 1")
    if not isinstance(near, numbers.Real) or isinstance(near, bool) or not math.isfinite(near) or near < 0:
        raise ConfigError(f"rasterize_gaussians: near={near!r}: expected a finite distance >= 0 (metres; Gaussians "
                          f"at camera z <= near are culled)")
    if tuple(intrinsics.shape) != (3, 3) or tuple(c2w.shape) != (4, 4):
        raise ConfigError(f"rasterize_gaussians: intrinsics {list(intrinsics.shape)}, c2w {list(c2w.shape)}: "
                          f"expected [3, 3] and [4, 4]")
    if background is not None and tuple(background.shape) != (gaussians.channels,):
        raise ConfigError(f"rasterize_gaussians: background {list(background.shape)}: expected "
                          f"[{gaussians.channels}] (one per channel)")
    named = {"means": gaussians.means, "rotations": gaussians.rotations, "features": gaussians.features,
             "intrinsics": intrinsics, "c2w": c2w, "background": background}
    for name, tensor in named.items():
        if tensor is not None and not all_finite(tensor.detach()):
            raise NonFiniteError(f"rasterize_gaussians: {name} holds NaN or Inf")
    fx, fy = float(intrinsics[0, 0]), float(intrinsics[1, 1])
    if not (fx > 0 and fy > 0):
        raise ConfigError(f"rasterize_gaussians: intrinsics fx={fx:g}, fy={fy:g}: expected focal lengths > 0 "
                          f"(pixels)")
    low, _ = _extremes("scales", gaussians.scales)
    if low < 0:
        raise ConfigError(f"rasterize_gaussians: scales hold {low:g}: expected standard deviations >= 0 (metres; a "
                          f"model storing logs passes exp)")
    low, high = _extremes("opacities", gaussians.opacities)
    if low < 0 or high > 1:
        raise ConfigError(f"rasterize_gaussians: opacities span [{low:g}, {high:g}]: expected values in [0, 1] (a "
                          f"model storing logits passes sigmoid)")


def strided_camera(camera: TargetCamera, stride: int) -> tuple[Tensor, int, int]:
    """``(intrinsics, height, width)`` of the grid of every ``stride``-th pixel's cell of ``camera`` (a cell's centre is
    the full image's pixel ``(j + 0.5) stride - 0.5``, as ``gpnerf_core.pixel_grid``): what a rasterizing family renders
    a view on at a render stride."""
    if stride < 1 or camera.height % stride or camera.width % stride:
        raise ConfigError(f"image size {camera.height}x{camera.width} is not divisible by the render stride {stride}")
    intrinsics = camera.intrinsics.clone()
    intrinsics[:2, :2] /= stride
    intrinsics[:2, 2] = (intrinsics[:2, 2] + 0.5) / stride - 0.5
    return intrinsics, camera.height // stride, camera.width // stride


def rasterize_gaussians(gaussians: Gaussians, *, intrinsics: Tensor, c2w: Tensor, height: int, width: int,
                        near: float = NEAR_CULL, background: Tensor | None = None, tile_size: int = 16,
                        backend: str = "auto") -> Rasterized:
    """Render ``gaussians`` into one pinhole view, differentiably in every Gaussian parameter.

    Args:
        gaussians: G activated Gaussians in the world frame; every tensor is cast to ``means``' dtype (float32 for a
            half-precision one, and always outside autocast: ``train.precision=bf16`` rasterizes in float32).
        intrinsics: ``[3, 3]`` pinhole matrix at ``height`` x ``width`` (pixel centres at integer coordinates).
        c2w: ``[4, 4]`` camera-to-world pose (OpenCV: x right, y down, z forward), metres.
        height, width: image size, pixels.
        near: Gaussians at camera z <= near (metres) are culled (``NEAR_CULL``, 0.2 m as the official 3DGS).
        background: ``[C]`` added as ``background * (1 - alpha)`` to the features, or None.
        tile_size: side of the square tiles, pixels (the result does not depend on it).
        backend: ``"torch"``, ``"numba"``, ``"gsplat"`` or ``"auto"`` (``choose_backend``).

    Raises:
        NonFiniteError: NaN or Inf in an input (named), or a covariance overflowing the dtype (every backend).
        ConfigError: an unknown backend, or one that cannot run on these tensors; a size that is not an int >= 1;
            ``near`` not finite and >= 0; ``fx`` or ``fy`` <= 0; a negative scale; an opacity outside [0, 1]; a
            wrong shape (docs/rasterizer.md's table of checks).
    """
    _check(gaussians, intrinsics, c2w, height, width, near, tile_size, background)
    name = choose_backend(backend, gaussians.means.device)
    with torch.autocast(gaussians.means.device.type, enabled=False):  # projection and blending need float32 at least
        return _rasterize(gaussians, intrinsics, c2w, height, width, near, background, tile_size, name)


def _rasterize(gaussians: Gaussians, intrinsics: Tensor, c2w: Tensor, height: int, width: int, near: float,
               background: Tensor | None, tile_size: int, name: str) -> Rasterized:
    dtype = gaussians.means.dtype if gaussians.means.dtype in (torch.float32, torch.float64) else torch.float32
    gaussians = Gaussians(*(getattr(gaussians, field.name).to(dtype) for field in fields(Gaussians)))
    if name == "numba" and not _needs_gradient(gaussians, intrinsics, c2w):
        projected, bins = project_and_bin_numba(gaussians, intrinsics, c2w, height, width, near, tile_size)
    else:
        projected = project_gaussians(gaussians, intrinsics, c2w, height, width, near)
        bins = bin_gaussians(projected, height, width, tile_size, fill_tiles_numba if name == "numba" else fill_tiles)
    features, depth, alpha = BACKENDS[name](projected.means2d, projected.conics, projected.opacities,
                                            gaussians.features, projected.depths, bins, height, width)
    if background is not None:
        features = features + background.to(dtype) * (1.0 - alpha)[..., None]
    return Rasterized(features=features, depth=depth, alpha=alpha, means2d=projected.means2d, radii=projected.radii,
                      culled_behind=projected.culled_behind, clamped=projected.clamped, backend=name)
