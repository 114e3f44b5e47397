"""The fast CPU compositor: ``numba_kernels`` wrapped in a ``torch.autograd.Function``.

The Function's inputs are the projected centres, conics, opacities, features and depths, so the projection's gradients
still come from autograd. The forward keeps each pixel's final transmittance and how far down its list it walked; the
backward walks back to front from there (as the official backward does) and writes one gradient row per (tile,
Gaussian) intersection from the kernel's threads, which ``index_add_`` sums per Gaussian: no two threads write one
place. A forward that a backward will follow keeps each tile's local table and block lists (about 16 int32 and 7
float64 per intersection), so the backward does not build them again (the same arrays: the same results).

Threads: the kernels release the GIL and run here on a thread pool of ``torch.get_num_threads()`` threads, tiles
dealt out from the most crowded down, a few chunks per thread. Not numba's ``parallel=True``: with its default OpenMP
layer, the torch work after one parallel kernel ran 5 times slower on a 2-core machine (a loop of sorts and matmuls:
8.7 ms before, 43 ms after; its workqueue layer: 8.9 ms), and the workqueue layer aborts the process when two Python
threads launch kernels at once. Pool threads wait without spinning, and any number of callers may use them.
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.geometry.gaussians.binning import TileBins
from gpnerf_core.geometry.gaussians.projection import ProjectedGaussians


@functools.cache
def kernels() -> ModuleType | None:
    """``numba_kernels``, imported on first use; None when numba cannot be imported here."""
    try:
        from gpnerf_core.geometry.gaussians import numba_kernels
    except ImportError:
        return None
    return numba_kernels


CHUNKS_PER_THREAD = 4
"""Tiles are dealt into this many chunks per thread, which the pool's threads take as they come free."""

_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}


def _over_tiles(kernel, offsets: Tensor, *arguments) -> None:
    """Run ``kernel(tiles, *arguments)`` over every tile, on ``torch.get_num_threads()`` threads."""
    threads = max(1, torch.get_num_threads())
    lengths = (offsets[1:] - offsets[:-1]).numpy()
    if threads == 1 or lengths.shape[0] < 2:
        kernel(np.arange(lengths.shape[0]), *arguments)
        return
    crowded_first = np.argsort(-lengths, kind="stable")
    count = min(threads * CHUNKS_PER_THREAD, lengths.shape[0])
    pool = _pools.get((os.getpid(), threads))  # a forked child makes its own threads
    if pool is None:
        pool = _pools[(os.getpid(), threads)] = ThreadPoolExecutor(threads, thread_name_prefix="gaussian-raster")
    chunks = [np.ascontiguousarray(crowded_first[i::count]) for i in range(count)]
    for future in [pool.submit(kernel, chunk, *arguments) for chunk in chunks]:
        future.result()


def _array(tensor: Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, depths, offsets, ids, height, width, tile_size):
        dtype = features.detach().numpy().dtype
        out_features = np.empty((height, width, features.shape[1]), dtype=dtype)
        out_depth = np.empty((height, width), dtype=dtype)
        out_transmittance = np.empty((height, width), dtype=dtype)
        walked = np.empty((height, width), dtype=np.int32)
        keep = any(ctx.needs_input_grad[:5])  # a backward will follow: it reads the tiles' tables and lists
        per_tile = kernels().blocks_per_tile(tile_size) if keep else 0
        kept = (np.empty((ids.shape[0] if keep else 0, 7)), np.empty(ids.shape[0] * per_tile, dtype=np.int32),
                np.empty((offsets.shape[0] - 1 if keep else 0, per_tile), dtype=np.int64))
        _over_tiles(kernels().forward_tiles, offsets,
                    *map(_array, (means2d, conics, opacities, features, depths, offsets, ids)), height, width,
                    tile_size, out_features, out_depth, out_transmittance, walked, keep, *kept)
        transmittance, walked = torch.from_numpy(out_transmittance), torch.from_numpy(walked)
        ctx.save_for_backward(means2d, conics, opacities, features, depths, offsets, ids, transmittance, walked)
        ctx.size = (height, width, tile_size)
        ctx.kept = kept
        return torch.from_numpy(out_features), torch.from_numpy(out_depth), 1.0 - transmittance

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_features, grad_depth, grad_alpha):
        means2d, conics, opacities, features, depths, offsets, ids, transmittance, walked = ctx.saved_tensors
        count, channels = ids.shape[0], features.shape[1]
        per_intersection = [torch.zeros(count, *shape, dtype=features.dtype)
                            for shape in ((2,), (3,), (), (channels,), ())]
        _over_tiles(
            kernels().backward_tiles, offsets,
            *map(_array, (means2d, conics, opacities, features, depths, offsets, ids)), *ctx.size,
            _array(transmittance), _array(walked), *ctx.kept, *map(_array, (grad_features, grad_depth, grad_alpha)),
            *(grad.numpy() for grad in per_intersection))
        grads = [torch.zeros_like(tensor).index_add_(0, ids, grad)
                 for tensor, grad in zip((means2d, conics, opacities, features, depths), per_intersection)]
        return (*grads, None, None, None, None, None)


def fill_tiles_numba(ids: Tensor, low: Tensor, high: Tensor, tiles_x: int, tiles_y: int) -> tuple[Tensor, Tensor]:
    """``binning.fill_tiles`` by the kernels' counting sort (the same lists, without sorting the intersections)."""
    offsets, listed = kernels().fill_tiles(*map(_array, (ids, low, high)), tiles_x, tiles_y)
    return torch.from_numpy(offsets), torch.from_numpy(listed)


def composite_numba(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
                    bins: TileBins, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """``torch_backend.composite_torch``'s contract, on CPU tensors of one float dtype, by the numba kernels."""
    return _Composite.apply(means2d, conics, opacities, features, depths, bins.offsets, bins.ids, height, width,
                            bins.tile_size)


def project_and_bin_numba(gaussians: Any, intrinsics: Tensor, c2w: Tensor, height: int, width: int, near: float,
                          tile_size: int) -> tuple[ProjectedGaussians, TileBins]:
    """``projection.project_gaussians`` and ``binning.bin_gaussians`` by one numba kernel, for a render without
    gradients (the projection's torch ops cost more than compositing a small view). The same lists; the footprints'
    sums in float64."""
    from gpnerf_core.geometry.gaussians.projection import (
        ALPHA_MIN, BOX_MARGIN, JACOBIAN_LIMIT, LOW_PASS, overflow_message,
    )

    dtype = gaussians.means.dtype
    rotation_cw = c2w[:3, :3].to(dtype).T.contiguous()
    (means2d, conics, depths, visible, radii, clamped, behind, overflowed, offsets, listed) = kernels().project_and_bin(
        *map(_array, (gaussians.means, gaussians.scales, gaussians.rotations, gaussians.opacities)),
        _array(intrinsics.to(torch.float64)), _array(rotation_cw.to(torch.float64)),
        _array(c2w[:3, 3].to(torch.float64)), height, width, float(near), tile_size, LOW_PASS, JACOBIAN_LIMIT,
        ALPHA_MIN, BOX_MARGIN)
    if overflowed:
        raise NonFiniteError(overflow_message(int(overflowed), dtype))
    projected = ProjectedGaussians(
        means2d=torch.from_numpy(means2d), conics=torch.from_numpy(conics), depths=torch.from_numpy(depths),
        opacities=gaussians.opacities, extents=torch.zeros(0), visible=torch.from_numpy(visible),
        radii=torch.from_numpy(radii), culled_behind=int(behind), clamped=int(clamped))
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    bins = TileBins(offsets=torch.from_numpy(offsets), ids=torch.from_numpy(listed), tile_size=tile_size,
                    tiles_x=tiles_x, tiles_y=tiles_y)
    return projected, bins
