"""A differentiable 3D Gaussian rasterizer (3DGS, Kerbl et al. 2023): EWA projection, tile binning, front-to-back
compositing of any channels, with a pure-torch reference, a numba CPU backend and gsplat's CUDA kernel
(docs/rasterizer.md).

    from gpnerf_core import Gaussians, rasterize_gaussians
    out = rasterize_gaussians(Gaussians(means, scales, rotations, opacities, features),
                              intrinsics=K, c2w=c2w, height=H, width=W)

Modules: ``records`` (what goes in and out), ``projection`` (EWA, culling, footprints), ``binning`` (tiles),
``torch_backend``, ``numba_backend`` with ``numba_kernels`` (imported on first use), ``gsplat_backend``, and
``rasterizer`` (the entry point and the backend choice); ``harmonics`` (view-dependent colour) and ``scene`` (Gaussians
in the world frame, the standard PLY).

The public Gaussian strategy a per-scene Gaussian family is built from (gsplat's ``splats`` and strategies):
``parameters`` (``GaussianParameters``: the trainable rows with their activations; ``rows_from_points``,
``rows_from_gaussians``), ``initialisation`` (SfM points or back-projected depth, starting scales, the scene's extent),
``density`` (``DefaultStrategy``: 3DGS's official schedule; ``BudgetedStrategy``: never more than a budget; the row
operations they are made of) and ``rows`` (``resize_parameter``: the optimizer's moments follow the rows).
"""

from gpnerf_core.geometry.gaussians.rasterizer import (
    BACKENDS, RASTERIZER_BACKENDS, choose_backend, rasterize_gaussians, strided_camera,
)
from gpnerf_core.geometry.gaussians.records import Gaussians, Rasterized

__all__ = ["BACKENDS", "Gaussians", "RASTERIZER_BACKENDS", "Rasterized", "choose_backend", "rasterize_gaussians",
           "strided_camera"]
