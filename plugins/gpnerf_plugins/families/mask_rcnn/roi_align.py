"""RoIAlign (He et al. 2017, Sec. 3) by bilinear sampling in plain torch, and its multi-scale form over FPN levels.

The arithmetic is torchvision's ``roi_align`` kernel (``torchvision/csrc/ops/cpu/roi_align_kernel.cpp``): each output
bin averages ``sampling_ratio`` x ``sampling_ratio`` bilinear samples at the centres of a regular sub-grid; a sample
more than one cell outside the map is 0, one within a cell of the edge reads the edge. ``aligned=True`` shifts boxes
by half a cell (detectron2's ``ROIAlignV2``: a box's continuous corner maps to the right place on the map).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _axis(start: Tensor, length: Tensor, bins: int, ratio: int, size: int) -> tuple[Tensor, ...]:
    """Along one axis of the map (``size`` cells): for ``[R]`` bin starts and box lengths, the ``[R, bins * ratio]``
    low and high cell indices, their weights and the validity of each sample."""
    steps = (torch.arange(bins * ratio, device=start.device, dtype=start.dtype) + 0.5) / ratio  # in bins
    coord = start[:, None] + steps[None, :] * (length / bins)[:, None]
    valid = (coord >= -1.0) & (coord <= size)
    coord = coord.clamp(min=0.0)
    low = coord.floor().long().clamp(max=size - 1)
    at_edge = low >= size - 1
    high = torch.where(at_edge, low, low + 1)
    coord = torch.where(at_edge, low.to(coord.dtype), coord)
    frac = coord - low.to(coord.dtype)
    return low, high, 1.0 - frac, frac, valid


def roi_align(features: Tensor, rois: Tensor, output_size: int, spatial_scale: float, sampling_ratio: int,
              aligned: bool) -> Tensor:
    """Pool each box of ``rois`` into an ``output_size`` x ``output_size`` grid of bilinear averages.

    Args:
        features: ``[N, C, H, W]`` one map per image.
        rois: ``[R, 5]`` ``(image index, x1, y1, x2, y2)`` in input pixels.
        spatial_scale: map cells per input pixel (1 / the level's stride).
        sampling_ratio: samples per bin along each axis (torchvision's Mask R-CNN: 2).
        aligned: shift the box by half a cell (detectron2's ``ROIAlignV2``); False keeps a box at least one cell wide.

    Returns:
        ``[R, C, output_size, output_size]``, differentiable in ``features`` (and in the box coordinates almost
        everywhere).
    """
    num, channels, height, width = features.shape
    if rois.shape[0] == 0:
        return features.new_zeros(0, channels, output_size, output_size)
    offset = 0.5 if aligned else 0.0
    boxes = rois[:, 1:] * spatial_scale - offset
    box_w, box_h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    if not aligned:
        box_w, box_h = box_w.clamp_min(1.0), box_h.clamp_min(1.0)
    ylo, yhi, yw0, yw1, yvalid = _axis(boxes[:, 1], box_h, output_size, sampling_ratio, height)
    xlo, xhi, xw0, xw1, xvalid = _axis(boxes[:, 0], box_w, output_size, sampling_ratio, width)
    flat = features.permute(0, 2, 3, 1).reshape(num * height * width, channels)
    base = rois[:, 0].long()[:, None, None] * (height * width)

    def corner(ys: Tensor, xs: Tensor) -> Tensor:  # [R, S, S, C]
        index = base + ys[:, :, None] * width + xs[:, None, :]
        return flat[index.reshape(-1)].reshape(*index.shape, channels)

    wy0, wy1 = yw0[:, :, None, None], yw1[:, :, None, None]
    wx0, wx1 = xw0[:, None, :, None], xw1[:, None, :, None]
    values = (wy0 * wx0 * corner(ylo, xlo) + wy0 * wx1 * corner(ylo, xhi)
              + wy1 * wx0 * corner(yhi, xlo) + wy1 * wx1 * corner(yhi, xhi))
    valid = (yvalid[:, :, None] & xvalid[:, None, :])[..., None]
    values = values * valid.to(values.dtype)
    r, s = values.shape[0], sampling_ratio
    values = values.reshape(r, output_size, s, output_size, s, channels).mean(dim=(2, 4))
    return values.permute(0, 3, 1, 2).contiguous()


def roi_levels(boxes: Tensor, min_level: int, max_level: int, canonical_size: float = 224.0,
               canonical_level: int = 4) -> Tensor:
    """FPN's level of each ``[R, 4]`` box (Lin et al. 2017, eq. 1; torchvision's ``LevelMapper``):
    ``floor(canonical_level + log2(sqrt(area) / canonical_size) + 1e-6)`` clamped to ``[min_level, max_level]``."""
    area = ((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])).clamp_min(1e-12)
    level = torch.floor(canonical_level + torch.log2(area.sqrt() / canonical_size) + 1e-6)
    return level.clamp(min_level, max_level).long()


def multiscale_roi_align(levels: list[Tensor], strides: list[int], rois: Tensor, output_size: int,
                         sampling_ratio: int, aligned: bool) -> Tensor:
    """RoIAlign of each box on its FPN level (``roi_levels``).

    Args:
        levels: ``[N, C, h_k, w_k]`` maps, finest first, at ``strides`` (powers of 2) pixels per cell.
        rois: ``[R, 5]`` as ``roi_align``.

    Returns:
        ``[R, C, output_size, output_size]`` in the order of ``rois``.
    """
    first = int(round(math.log2(strides[0])))
    assignment = roi_levels(rois[:, 1:], first, first + len(levels) - 1) - first
    out = levels[0].new_zeros(rois.shape[0], levels[0].shape[1], output_size, output_size)
    for k, (level, stride) in enumerate(zip(levels, strides)):
        chosen = torch.where(assignment == k)[0]
        if len(chosen):
            out[chosen] = roi_align(level, rois[chosen], output_size, 1.0 / stride, sampling_ratio, aligned)
    return out
