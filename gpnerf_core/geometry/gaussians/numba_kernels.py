"""Numba CPU kernels: the tile compositor forward (front to back) and backward (back to front), tile by tile.

Imported only by ``numba_backend`` when it first runs (numba's import and compilation stay out of ``import
gpnerf_core``); compiled once per dtype and cached on disk (``cache=True``). The kernels release the GIL and take a
list of tiles, so ``numba_backend`` runs them on its own threads (no numba threading layer: see there). Arrays are
numpy views of contiguous tensors: ``means2d [G, 2]``, ``conics [G, 3]``, ``opacities [G]``, ``features [G, C]``,
``depths [G]``, one float dtype; ``offsets [T + 1]`` and ``ids [N]`` int64 as ``binning.TileBins`` holds them. Pixel
centres are at integer coordinates; a pixel's sums are kept in float64.

A tile first copies its Gaussians' centres, conics and opacities into one local float64 table, with the ``power``
under which ``o exp(power)`` is surely below 1/255 (``ln(1 / (255 o))`` less a hair), and lists them again per 4 x 4
block of its pixels (those whose footprint box, ``projection``'s, touches the block; the others cannot reach its
pixels). A pixel walks its block's list in chunks: a branch-free pass keeps the Gaussians whose ``power`` clears the
cut (most do not, and a data-dependent branch per Gaussian cost more than its arithmetic), and only those get an
``exp`` and the official tests, exactly as ``torch_backend`` makes them. The forward kernel at 24k Gaussians, 35
channels, 96 x 128, one thread (docs/rasterizer.md): 154 ms as a plain per-Gaussian loop, 64 ms with the local table
and the cut, 39 ms with the chunks, about 35 ms with the blocks. ``fill_tiles`` is the binning's counting sort.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gpnerf_core.geometry.gaussians.projection import ALPHA_MAX, ALPHA_MIN, BOX_MARGIN, TRANSMITTANCE_MIN

SURELY_BELOW = 1e-9
"""Slack on the ``power`` cut, far above float64 rounding of ``log`` and ``exp``."""

U, V, A, B, C, OPACITY, CUT = range(7)
"""Columns of a tile's local table."""

CHUNK = 64
"""Gaussians a pixel sifts at once."""

BLOCK = 4
"""Side of the pixel blocks a tile lists its Gaussians for."""

CHANNEL_MATH = {"reassoc", "contract"}
"""LLVM may reorder and fuse the channel loops' sums (so it vectorizes them); nothing else is relaxed."""


@njit(nogil=True, cache=True)
def _table(means2d, conics, opacities, ids, start, end, table):
    """Fill ``table [n, 7]`` float64 (and return it): u, v, conic a, b, c, opacity and the power cut of the tile's
    Gaussians ``ids[start:end]``."""
    for j in range(end - start):
        gaussian = ids[start + j]
        opacity = opacities[gaussian]
        table[j, U], table[j, V] = means2d[gaussian, 0], means2d[gaussian, 1]
        table[j, A], table[j, B], table[j, C] = conics[gaussian, 0], conics[gaussian, 1], conics[gaussian, 2]
        table[j, OPACITY] = opacity
        table[j, CUT] = math.log(ALPHA_MIN / opacity) - SURELY_BELOW if opacity > 0.0 else np.inf
    return table


@njit(nogil=True, cache=True)
def _blocks(table, x0, y0, columns, rows, lists, counts):
    """Fill ``lists [blocks, n]`` int32 and ``counts [blocks]`` (and return them): per ``BLOCK`` x ``BLOCK`` block of the tile's ``rows`` x
    ``columns`` pixels from (x0, y0), row-major, the local Gaussians (in order) whose footprint box touches it: the box
    of ``d^T conic d <= 2 ln(255 o)``, half-widths ``sqrt(2 ln(255 o) Sigma'_uu)`` (``Sigma' = conic^-1``) widened
    as ``projection`` widens them."""
    across = (columns + BLOCK - 1) // BLOCK
    counts[:] = 0
    for j in range(table.shape[0]):
        reach = 2.0 * (-table[j, CUT] - SURELY_BELOW)  # 2 ln(255 o): k^2
        if reach < 0.0:
            continue
        det = table[j, A] * table[j, C] - table[j, B] * table[j, B]
        first_col, last_col, first_row, last_row = 0, columns - 1, 0, rows - 1
        if det > 0.0:  # else (rounding of a needle's conic): every block
            half_u = math.sqrt(reach * table[j, C] / det) * (1.0 + 1e-6) + BOX_MARGIN
            half_v = math.sqrt(reach * table[j, A] / det) * (1.0 + 1e-6) + BOX_MARGIN
            first_col = max(first_col, math.ceil(table[j, U] - half_u) - x0)
            last_col = min(last_col, math.floor(table[j, U] + half_u) - x0)
            first_row = max(first_row, math.ceil(table[j, V] - half_v) - y0)
            last_row = min(last_row, math.floor(table[j, V] + half_v) - y0)
        for block_row in range(first_row // BLOCK, last_row // BLOCK + 1) if first_row <= last_row else range(0):
            for block_col in range(first_col // BLOCK, last_col // BLOCK + 1) if first_col <= last_col else range(0):
                block = block_row * across + block_col
                lists[block, counts[block]] = j
                counts[block] += 1
    return lists, counts


def blocks_per_tile(tile_size: int) -> int:
    """How many ``BLOCK`` x ``BLOCK`` blocks a tile has at most: the rows of ``kept_counts`` a forward keeps."""
    return ((tile_size + BLOCK - 1) // BLOCK) ** 2


@njit(nogil=True, cache=True)
def _tile_lists(means2d, conics, opacities, ids, start, end, x0, y0, columns, rows, tile, keep, kept_table,
                kept_lists, kept_counts):
    """The tile's table and block lists (``_table``, ``_blocks``): built in the ``kept_*`` arrays when ``keep``
    (table rows ``start:end``, lists from ``start * blocks_per_tile``, counts in row ``tile``), so the backward reads
    them instead of building them again; in fresh arrays otherwise."""
    blocks = ((columns + BLOCK - 1) // BLOCK) * ((rows + BLOCK - 1) // BLOCK)
    n = end - start
    if keep:
        table = kept_table[start:end]
        lists = kept_lists[start * kept_counts.shape[1]:start * kept_counts.shape[1] + blocks * n].reshape((blocks, n))
        counts = kept_counts[tile, :blocks]
    else:
        table = np.empty((n, 7))
        lists = np.empty((blocks, n), dtype=np.int32)
        counts = np.empty(blocks, dtype=np.int64)
    _table(means2d, conics, opacities, ids, start, end, table)
    _blocks(table, x0, y0, columns, rows, lists, counts)
    return table, lists, counts


@njit(nogil=True, cache=True, fastmath=CHANNEL_MATH)
def _channels_back(grads, features, gaussian, rest, alpha, weight, out_features, k):
    """One Gaussian's channels on the way back, f = ``features[gaussian]``: ``out_features[k] += weight * grads`` (its
    features' gradient), the rest behind it ``rest += alpha (f - rest)``; returns ``grads . (f - rest_before)``."""
    dot = 0.0
    for channel in range(rest.shape[0]):
        difference = features[gaussian, channel] - rest[channel]
        dot += grads[channel] * difference
        rest[channel] += alpha * difference
        out_features[k, channel] += weight * grads[channel]
    return dot


@njit(nogil=True, cache=True)
def fill_tiles(ids, low, high, tiles_x, tiles_y):
    """``binning.fill_tiles``'s lists by a counting sort: ``(offsets [T + 1], listed ids [N])`` of Gaussians ``ids``
    (front to back) over the tile rectangles ``low [n, 2]`` ... ``high [n, 2]``."""
    offsets = np.zeros(tiles_x * tiles_y + 1, dtype=np.int64)
    for i in range(ids.shape[0]):
        for row in range(low[i, 1], high[i, 1] + 1):
            for col in range(low[i, 0], high[i, 0] + 1):
                offsets[row * tiles_x + col + 1] += 1
    for tile in range(tiles_x * tiles_y):
        offsets[tile + 1] += offsets[tile]
    cursor = offsets[:-1].copy()
    listed = np.empty(offsets[-1], dtype=np.int64)
    for i in range(ids.shape[0]):
        for row in range(low[i, 1], high[i, 1] + 1):
            for col in range(low[i, 0], high[i, 0] + 1):
                tile = row * tiles_x + col
                listed[cursor[tile]] = ids[i]
                cursor[tile] += 1
    return offsets, listed


@njit(nogil=True, cache=True, inline="always")
def _sift(table, listed, low, high, px, py, found, backwards):
    """Write into ``found`` the positions m in ``[low, high)`` of the block list ``listed`` whose Gaussian's power at
    pixel (px, py) lies in [cut, 0] (in order, or in reverse order); return how many. No branch depends on the data."""
    count = 0
    for step in range(high - low):
        m = high - 1 - step if backwards else low + step
        j = listed[m]
        dx, dy = table[j, U] - px, table[j, V] - py
        power = -0.5 * (table[j, A] * dx * dx + table[j, C] * dy * dy) - table[j, B] * dx * dy
        found[count] = m
        count += (power >= table[j, CUT]) & (power <= 0.0)
    return count


@njit(nogil=True, cache=True, inline="always")
def _alpha(table, j, px, py):
    """(alpha, exp(power), dx, dy) of local Gaussian j at pixel (px, py), d = centre - pixel; alpha 0 if skipped."""
    dx, dy = table[j, U] - px, table[j, V] - py
    power = -0.5 * (table[j, A] * dx * dx + table[j, C] * dy * dy) - table[j, B] * dx * dy
    if power < table[j, CUT] or power > 0.0:
        return 0.0, 0.0, dx, dy
    gauss = math.exp(power)
    alpha = min(ALPHA_MAX, table[j, OPACITY] * gauss)
    if alpha < ALPHA_MIN:
        return 0.0, gauss, dx, dy
    return alpha, gauss, dx, dy


@njit(nogil=True, cache=True)
def forward_tiles(tiles, means2d, conics, opacities, features, depths, offsets, ids, height, width, tile_size,
                  out_features, out_depth, out_transmittance, out_walked, keep, kept_table, kept_lists, kept_counts):
    """Composite the ``tiles`` (indices) into ``out_features [H, W, C]``, ``out_depth [H, W]``, the final
    transmittance ``[H, W]`` and ``out_walked [H, W]`` int32: how far down its block's list the pixel's last
    composited Gaussian is (1-based; 0: none). With ``keep``, each tile's table and block lists are left in
    ``kept_table [N, 7]`` float64, ``kept_lists [N * blocks_per_tile]`` int32 and ``kept_counts [T,
    blocks_per_tile]`` int64 for ``backward_tiles`` (``_tile_lists``); without, those may be empty."""
    tiles_x = (width + tile_size - 1) // tile_size
    channels = features.shape[1]
    accumulated = np.empty(channels)
    found = np.empty(CHUNK, dtype=np.int64)
    for tile in tiles:
        start, end = offsets[tile], offsets[tile + 1]
        y0, x0 = (tile // tiles_x) * tile_size, (tile % tiles_x) * tile_size
        columns, rows = min(tile_size, width - x0), min(tile_size, height - y0)
        table, lists, counts = _tile_lists(means2d, conics, opacities, ids, start, end, x0, y0, columns, rows, tile,
                                           keep, kept_table, kept_lists, kept_counts)
        across = (columns + BLOCK - 1) // BLOCK
        for py in range(y0, y0 + rows):
            for px in range(x0, x0 + columns):
                block = ((py - y0) // BLOCK) * across + (px - x0) // BLOCK
                listed, length = lists[block], counts[block]
                transmittance, depth, walked = 1.0, 0.0, 0
                accumulated[:] = 0.0
                low, stopped = 0, False
                while low < length and not stopped:
                    high = min(low + CHUNK, length)
                    for q in range(_sift(table, listed, low, high, px, py, found, False)):
                        m = found[q]
                        j = listed[m]
                        alpha, _, _, _ = _alpha(table, j, px, py)
                        if alpha == 0.0:
                            continue
                        after = transmittance * (1.0 - alpha)
                        if after < TRANSMITTANCE_MIN:
                            stopped = True
                            break
                        weight = alpha * transmittance
                        gaussian = ids[start + j]
                        for channel in range(channels):
                            accumulated[channel] += weight * features[gaussian, channel]
                        depth += weight * depths[gaussian]
                        transmittance = after
                        walked = m + 1
                    low = high
                for channel in range(channels):
                    out_features[py, px, channel] = accumulated[channel]
                out_depth[py, px] = depth
                out_transmittance[py, px] = transmittance
                out_walked[py, px] = walked


@njit(nogil=True, cache=True)
def backward_tiles(tiles, means2d, conics, opacities, features, depths, offsets, ids, height, width, tile_size,
                   transmittance, walked, kept_table, kept_lists, kept_counts, grad_features, grad_depth, grad_alpha,
                   out_means2d, out_conics, out_opacities, out_features, out_depths):
    """Per-intersection gradients (row k of each ``out_*`` belongs to ``ids[k]``; zero-filled by the caller) of the
    loss whose gradients on the outputs are ``grad_features [H, W, C]``, ``grad_depth [H, W]``, ``grad_alpha [H, W]``.

    Walks each pixel's block list back to front from its last composited Gaussian, recovering
    ``T_i = T_{i+1} / (1 - a_i)`` and the normalised rest behind it ``S_{i+1}``: ``dL/da_i = T_i (g_F . (f_i - S_{i+1}) + g_D (z_i - SD_{i+1}))
    + g_A T_final / (1 - a_i)``; then through ``a = o exp(power)`` (zero where the 0.99 cap binds). Each tile's
    table and block lists are the forward's (``forward_tiles`` with ``keep``).
    """
    tiles_x = (width + tile_size - 1) // tile_size
    channels = features.shape[1]
    rest = np.empty(channels)
    grads = np.empty(channels)
    found = np.empty(CHUNK, dtype=np.int64)
    for tile in tiles:
        start = offsets[tile]
        y0, x0 = (tile // tiles_x) * tile_size, (tile % tiles_x) * tile_size
        end = offsets[tile + 1]
        columns, rows = min(tile_size, width - x0), min(tile_size, height - y0)
        blocks, n = ((columns + BLOCK - 1) // BLOCK) * ((rows + BLOCK - 1) // BLOCK), end - start
        table = kept_table[start:end]
        base = start * kept_counts.shape[1]
        lists = kept_lists[base:base + blocks * n].reshape((blocks, n))
        across = (columns + BLOCK - 1) // BLOCK
        for py in range(y0, y0 + rows):
            for px in range(x0, x0 + columns):
                listed = lists[((py - y0) // BLOCK) * across + (px - x0) // BLOCK]
                last = walked[py, px]
                if last == 0:
                    continue
                final = transmittance[py, px]
                after = final
                rest[:] = 0.0
                rest_depth = 0.0
                g_depth, g_alpha = grad_depth[py, px], grad_alpha[py, px]
                for channel in range(channels):
                    grads[channel] = grad_features[py, px, channel]
                high = last
                while high > 0:
                    low = max(0, high - CHUNK)
                    for q in range(_sift(table, listed, low, high, px, py, found, True)):
                        j = listed[found[q]]
                        alpha, gauss, dx, dy = _alpha(table, j, px, py)
                        if alpha == 0.0:
                            continue
                        k = start + j
                        gaussian = ids[k]
                        before = after / (1.0 - alpha)
                        weight = alpha * before
                        dot = _channels_back(grads, features, gaussian, rest, alpha, weight, out_features, k)
                        depth = depths[gaussian]
                        out_depths[k] += weight * g_depth
                        d_alpha = before * (dot + g_depth * (depth - rest_depth)) + g_alpha * final / (1.0 - alpha)
                        rest_depth = alpha * depth + (1.0 - alpha) * rest_depth
                        after = before
                        raw = table[j, OPACITY] * gauss
                        if raw > ALPHA_MAX:  # the cap binds: alpha does not move with o or power
                            continue
                        out_opacities[k] += gauss * d_alpha
                        d_power = raw * d_alpha
                        a, b, c = table[j, A], table[j, B], table[j, C]
                        out_means2d[k, 0] -= d_power * (a * dx + b * dy)
                        out_means2d[k, 1] -= d_power * (b * dx + c * dy)
                        out_conics[k, 0] -= 0.5 * d_power * dx * dx
                        out_conics[k, 1] -= d_power * dx * dy
                        out_conics[k, 2] -= 0.5 * d_power * dy * dy
                    high = low


@njit(nogil=True, cache=True)
def project_and_bin(means, scales, rotations, opacities, intrinsics, rotation_cw, origin, height, width, near,
                    tile_size, low_pass, limit, alpha_min, box_margin):
    """``projection.project_gaussians`` then ``binning.bin_gaussians`` in one pass per Gaussian, for rendering without
    gradients: the same footprints, culling and front-to-back lists (the sums in float64, so a few ulps from torch's).

    ``rotation_cw`` ``[3, 3]`` world-to-camera rotation, ``origin`` ``[3]`` the camera centre. Returns ``(means2d
    [G, 2], conics [G, 3], depths [G], visible [G] bool, radii [G] int32, clamped, culled_behind, overflowed, offsets,
    listed)``; ``overflowed`` counts the Gaussians in front whose 2D covariance or its determinant does not fit the
    dtype (the caller refuses those, as ``project_gaussians`` does).
    """
    count = means.shape[0]
    dtype = means.dtype
    means2d = np.zeros((count, 2), dtype=dtype)
    conics = np.zeros((count, 3), dtype=dtype)
    depths = np.ones(count, dtype=dtype)
    visible = np.zeros(count, dtype=np.bool_)
    radii = np.zeros(count, dtype=np.int32)
    low = np.zeros((count, 2), dtype=np.int64)
    high = np.zeros((count, 2), dtype=np.int64)
    fx, skew, cx = intrinsics[0, 0], intrinsics[0, 1], intrinsics[0, 2]
    fy, cy = intrinsics[1, 1], intrinsics[1, 2]
    spare_x, spare_y = (limit - 1.0) * 0.5 * width / fx, (limit - 1.0) * 0.5 * height / fy
    lo_x, hi_x = -(cx + 0.5) / fx - spare_x, (width - 0.5 - cx) / fx + spare_x
    lo_y, hi_y = -(cy + 0.5) / fy - spare_y, (height - 0.5 - cy) / fy + spare_y
    eps = np.finfo(dtype).eps
    largest = np.finfo(dtype).max
    tiles_x, tiles_y = (width + tile_size - 1) // tile_size, (height + tile_size - 1) // tile_size
    clamped, behind, overflowed = 0, 0, 0
    local = np.empty((3, 3))
    world = np.empty((3, 3))
    for i in range(count):
        d0, d1, d2 = means[i, 0] - origin[0], means[i, 1] - origin[1], means[i, 2] - origin[2]
        x = rotation_cw[0, 0] * d0 + rotation_cw[0, 1] * d1 + rotation_cw[0, 2] * d2
        y = rotation_cw[1, 0] * d0 + rotation_cw[1, 1] * d1 + rotation_cw[1, 2] * d2
        z = rotation_cw[2, 0] * d0 + rotation_cw[2, 1] * d1 + rotation_cw[2, 2] * d2
        if not z > near:
            behind += 1
            continue
        depths[i] = z
        u = (fx * x + skew * y) / z + cx
        v = fy * y / z + cy
        means2d[i, 0], means2d[i, 1] = u, v
        tx = z * min(max(x / z, lo_x), hi_x)
        ty = z * min(max(y / z, lo_y), hi_y)
        # J = K2 P with P = [[1/z, 0, -tx/z^2], [0, 1/z, -ty/z^2]]
        j00, j01, j02 = fx / z, skew / z, -(fx * tx + skew * ty) / (z * z)
        j10, j11, j12 = intrinsics[1, 0] / z, fy / z, -(intrinsics[1, 0] * tx + fy * ty) / (z * z)
        qw, qx, qy, qz = rotations[i, 0], rotations[i, 1], rotations[i, 2], rotations[i, 3]
        norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        local[0, 0], local[0, 1], local[0, 2] = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        local[1, 0], local[1, 1], local[1, 2] = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        local[2, 0], local[2, 1], local[2, 2] = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        for r in range(3):
            for k in range(3):
                world[r, k] = (rotation_cw[r, 0] * local[0, k] + rotation_cw[r, 1] * local[1, k]
                               + rotation_cw[r, 2] * local[2, k]) * scales[i, k]
        u0 = j00 * world[0, 0] + j01 * world[1, 0] + j02 * world[2, 0]
        u1 = j00 * world[0, 1] + j01 * world[1, 1] + j02 * world[2, 1]
        u2 = j00 * world[0, 2] + j01 * world[1, 2] + j02 * world[2, 2]
        v0 = j10 * world[0, 0] + j11 * world[1, 0] + j12 * world[2, 0]
        v1 = j10 * world[0, 1] + j11 * world[1, 1] + j12 * world[2, 1]
        v2 = j10 * world[0, 2] + j11 * world[1, 2] + j12 * world[2, 2]
        a = u0 * u0 + u1 * u1 + u2 * u2
        b = u0 * v0 + u1 * v1 + u2 * v2
        c = v0 * v0 + v1 * v1 + v2 * v2
        c0, c1, c2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        det = c0 * c0 + c1 * c1 + c2 * c2
        if det <= 8 * eps * (a + c) ** 2:
            clamped += 1
        det_filtered = det + low_pass * (a + c) + low_pass * low_pass
        if not (a <= largest and c <= largest and abs(b) <= largest and det_filtered <= largest):  # Inf or NaN in the dtype
            overflowed += 1
            continue
        a, c = a + low_pass, c + low_pass
        conics[i, 0], conics[i, 1], conics[i, 2] = c / det_filtered, -b / det_filtered, a / det_filtered
        opacity = opacities[i]
        if not opacity >= alpha_min:
            continue
        reach = math.sqrt(2.0 * math.log(max(opacity / alpha_min, 1.0)))
        half_u, half_v = reach * math.sqrt(a) + box_margin, reach * math.sqrt(c) + box_margin
        first_u, last_u = math.ceil(u - half_u), math.floor(u + half_u)
        first_v, last_v = math.ceil(v - half_v), math.floor(v + half_v)
        if first_u > width - 1 or last_u < 0 or first_u > last_u or first_v > height - 1 or last_v < 0 \
                or first_v > last_v:
            continue
        visible[i] = True
        spread = math.sqrt(max(((a - c) / 2) ** 2 + b * b, 0.1))
        radii[i] = min(math.ceil(3.0 * math.sqrt((a + c) / 2 + spread)), 2**30)
        low[i, 0] = min(max(first_u, 0), width - 1) // tile_size
        low[i, 1] = min(max(first_v, 0), height - 1) // tile_size
        high[i, 0] = min(max(last_u, 0), width - 1) // tile_size
        high[i, 1] = min(max(last_v, 0), height - 1) // tile_size
    ids = np.nonzero(visible)[0]
    ids = ids[np.argsort(depths[ids], kind="mergesort")]  # front to back, ties by index (stable)
    offsets, listed = fill_tiles(ids, low[ids], high[ids], tiles_x, tiles_y)
    return means2d, conics, depths, visible, radii, clamped, behind, overflowed, offsets, listed
