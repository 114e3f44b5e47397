"""Pictures a run writes: label colour maps, error maps, depth, PCA of features, panels and training curves.

Everything returns ``uint8`` numpy arrays and touches no file, except :func:`save_image` and
:func:`plot_training_curves`, which write atomically through :mod:`gpnerf_core.runtime.io`.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.colors
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

from gpnerf_core.runtime.io import atomic_save_png, atomic_write_bytes
from gpnerf_core.runtime.finite import all_finite

CORRECT_COLOUR = (40, 170, 70)
"""Error-map colour of a correctly labelled pixel (green)."""
WRONG_COLOUR = (220, 40, 40)
"""Error-map colour of a wrongly labelled pixel (red)."""
IGNORED_COLOUR = (0, 0, 0)
"""Colour of pixels whose ground truth is the ignore label, in every label picture (black)."""

_MAX_PALETTE = 2**24 - 1


def _to_numpy(array: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(array, Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def label_palette(num_classes: int) -> np.ndarray:
    """A fixed, distinct, non-black colour per class.

    Class ``k`` gets the PASCAL-VOC bit-interleaved colour of ``k + 1``: the bits of ``k + 1`` are dealt to the
    R, G, B channels from the most significant bit down, so every class up to 2^24 - 2 has its own colour and
    black stays free for ignored pixels.

    Returns:
        ``[num_classes, 3]`` uint8.
    """
    if not 1 <= num_classes <= _MAX_PALETTE - 1:
        raise ValueError(f"num_classes must be in [1, {_MAX_PALETTE - 1}], got {num_classes}")
    ids = np.arange(1, num_classes + 1, dtype=np.int64)
    colours = np.zeros((num_classes, 3), dtype=np.int64)
    for bit in range(8):
        for channel in range(3):
            colours[:, channel] |= ((ids >> (3 * bit + channel)) & 1) << (7 - bit)
    return colours.astype(np.uint8)


def colorize_labels(
    labels: Tensor | np.ndarray, num_classes: int, ignore_index: int | None = None
) -> np.ndarray:
    """Colour a label map with :func:`label_palette`.

    Args:
        labels: ``[H, W]`` integer classes in ``[0, num_classes)`` or ``ignore_index``.
        num_classes: K.
        ignore_index: label drawn black (None: none).

    Returns:
        ``[H, W, 3]`` uint8.
    """
    array = _to_numpy(labels)
    if array.ndim != 2 or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"labels must be an integer [H, W] map, got {array.dtype} of shape {list(array.shape)}")
    array = array.astype(np.int64)
    valid = np.ones(array.shape, dtype=bool) if ignore_index is None else array != ignore_index
    bad = valid & ((array < 0) | (array >= num_classes))
    if bad.any():
        raise ValueError(
            f"label {int(array[bad][0])} is neither in [0, {num_classes}) nor the ignore index {ignore_index}"
        )
    out = np.zeros((*array.shape, 3), dtype=np.uint8)
    out[valid] = label_palette(num_classes)[array[valid]]
    return out


def class_legend(names: Sequence[str], swatch: int = 12, gap: int = 3) -> np.ndarray:
    """The legend of :func:`colorize_labels`: one row per class, its colour swatch and its name, on white.

    Args:
        names: class names, ids 0..K-1 in order.
        swatch: side of each colour square in pixels; gap: white pixels around rows.

    Returns:
        ``[K * (swatch + gap) + gap, W, 3]`` uint8, W fitting the longest name.
    """
    if not names:
        raise ValueError("class_legend needs at least one class name")
    palette = label_palette(len(names))
    font = _font(max(8, swatch - 1))
    widths = [ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(str(name), font=font) for name in names]
    width = int(gap * 3 + swatch + max(widths)) + 1
    canvas = Image.new("RGB", (width, len(names) * (swatch + gap) + gap), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for index, name in enumerate(names):
        top = gap + index * (swatch + gap)
        draw.rectangle((gap, top, gap + swatch - 1, top + swatch - 1), fill=tuple(int(c) for c in palette[index]))
        draw.text((2 * gap + swatch, top - 1), str(name), fill=(0, 0, 0), font=font)
    return np.asarray(canvas, dtype=np.uint8).copy()


def colorize_instances(ids: Tensor | np.ndarray) -> np.ndarray:
    """Colour an instance-id map: id ``i`` gets hue ``frac(0.618034 * i)`` (golden-ratio steps keep neighbouring ids
    apart), the same colour in every picture.

    Args:
        ids: ``[H, W]`` non-negative integer ids.

    Returns:
        ``[H, W, 3]`` uint8.
    """
    array = _to_numpy(ids)
    if array.ndim != 2 or not np.issubdtype(array.dtype, np.integer) or (array.size and array.min() < 0):
        raise ValueError(
            f"instance ids must be a non-negative integer [H, W] map, got {array.dtype} {list(array.shape)}"
        )
    unique, inverse = np.unique(array.astype(np.int64), return_inverse=True)
    hsv = np.stack([(unique * 0.618034) % 1.0, np.full(len(unique), 0.7), np.full(len(unique), 0.95)], axis=-1)
    colours = (matplotlib.colors.hsv_to_rgb(hsv) * 255.0 + 0.5).astype(np.uint8)
    return colours[inverse.reshape(array.shape)]


def error_map(
    pred_labels: Tensor | np.ndarray, gt_labels: Tensor | np.ndarray, ignore_index: int | None = None
) -> np.ndarray:
    """Correct / wrong / ignored pixels of a label prediction.

    Args:
        pred_labels, gt_labels: ``[H, W]`` integer maps of the same shape.
        ignore_index: GT label drawn as ignored.

    Returns:
        ``[H, W, 3]`` uint8 in :data:`CORRECT_COLOUR`, :data:`WRONG_COLOUR` and :data:`IGNORED_COLOUR`.
    """
    pred, gt = _to_numpy(pred_labels), _to_numpy(gt_labels)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise ValueError(f"pred and gt must be [H, W] maps of one shape, got {list(pred.shape)} and {list(gt.shape)}")
    out = np.empty((*gt.shape, 3), dtype=np.uint8)
    out[:] = WRONG_COLOUR
    out[pred == gt] = CORRECT_COLOUR
    if ignore_index is not None:
        out[gt == ignore_index] = IGNORED_COLOUR
    return out


def _apply_colormap(values: np.ndarray, cmap: str) -> np.ndarray:
    """Map ``values`` in [0, 1] through a matplotlib colormap to uint8 RGB."""
    rgba = matplotlib.colormaps[cmap](np.clip(values, 0.0, 1.0))
    return np.round(rgba[..., :3] * 255.0).astype(np.uint8)


def rgb_error_map(
    pred_rgb: Tensor | np.ndarray, gt_rgb: Tensor | np.ndarray, max_error: float = 0.25, cmap: str = "inferno"
) -> np.ndarray:
    """Per-pixel absolute colour error as a heat map.

    Args:
        pred_rgb, gt_rgb: ``[H, W, 3]`` colours, clamped to [0, 1] before comparing.
        max_error: error (mean over channels, in [0, 1] units) shown at the top of the colour scale; larger errors
            saturate. A fixed scale keeps pictures of different runs comparable.
        cmap: matplotlib colormap name.

    Returns:
        ``[H, W, 3]`` uint8.
    """
    pred = np.clip(_to_numpy(pred_rgb).astype(np.float64), 0.0, 1.0)
    gt = np.clip(_to_numpy(gt_rgb).astype(np.float64), 0.0, 1.0)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"pred and gt must be [H, W, 3] of one shape, got {list(pred.shape)} and {list(gt.shape)}")
    if max_error <= 0:
        raise ValueError(f"max_error must be > 0, got {max_error}")
    error = np.abs(pred - gt).mean(axis=2)
    return _apply_colormap(error / max_error, cmap)


def depth_to_color(
    depth: Tensor | np.ndarray, near: float, far: float, cmap: str = "turbo"
) -> np.ndarray:
    """Colour a depth map linearly between ``near`` and ``far`` (metres); unknown depth (<= 0 or not finite) is black.

    Args:
        depth: ``[H, W]`` metres.

    Returns:
        ``[H, W, 3]`` uint8.
    """
    values = _to_numpy(depth).astype(np.float64)
    if values.ndim != 2:
        raise ValueError(f"depth must be [H, W], got shape {list(values.shape)}")
    if not far > near:
        raise ValueError(f"depth colouring needs far > near, got near={near}, far={far}")
    known = np.isfinite(values) & (values > 0)
    out = _apply_colormap((np.where(known, values, near) - near) / (far - near), cmap)
    out[~known] = 0
    return out


def pca_rgb(features: Tensor | np.ndarray) -> np.ndarray:
    """Show a feature map through its top-3 principal components.

    Features are centred over pixels; the components are the leading eigenvectors of their covariance (exact,
    not randomised). Each component's sign is fixed so that its largest-magnitude loading is positive, so the
    same input always gives the same picture. Each projection is min-max normalised to [0, 255]; with fewer
    than 3 channels the missing colour channels are 0.

    Args:
        features: ``[C, h, w]`` real features.

    Returns:
        ``[h, w, 3]`` uint8.
    """
    tensor = torch.as_tensor(features).detach()
    if tensor.ndim != 3 or not tensor.dtype.is_floating_point:
        raise ValueError(f"features must be a float [C, h, w] map, got {tensor.dtype} of shape {list(tensor.shape)}")
    channels, height, width = tensor.shape
    x = tensor.to(torch.float64).reshape(channels, -1).T
    if not all_finite(x):
        raise ValueError("features contain NaN or Inf values")
    x = x - x.mean(dim=0, keepdim=True)
    _, vectors = torch.linalg.eigh(x.T @ x)
    k = min(3, channels)
    components = vectors[:, -k:].flip(-1)
    lead = components.gather(0, components.abs().argmax(dim=0, keepdim=True))
    components = components * torch.where(lead < 0, -1.0, 1.0).to(components)
    projected = torch.zeros(x.shape[0], 3, dtype=torch.float64, device=x.device)
    projected[:, :k] = x @ components
    low = projected.min(dim=0).values
    span = projected.max(dim=0).values - low
    scaled = torch.where(span > 0, (projected - low) / torch.where(span > 0, span, 1.0), torch.zeros_like(projected))
    image = torch.round(scaled * 255.0).to(torch.uint8).reshape(height, width, 3)
    return image.cpu().numpy()


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError):
        # Pillow without FreeType: the fixed bitmap font.
        return ImageFont.load_default()


def side_by_side(
    images: Sequence[np.ndarray], labels: Sequence[str] | None = None, gap: int = 4, title_height: int = 16
) -> np.ndarray:
    """Place images left to right on a white panel, each with a small title above it.

    Args:
        images: uint8 ``[H_i, W_i]`` or ``[H_i, W_i, 3]`` arrays (sizes may differ; shorter ones are top-aligned).
        labels: one title per image, or None for no titles.
        gap: white pixels between images.
        title_height: height of the title strip in pixels.

    Returns:
        ``[title_height + max H_i, sum W_i + gap * (n - 1), 3]`` uint8 (no title strip when ``labels`` is None).
    """
    if not images:
        raise ValueError("side_by_side needs at least one image")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"got {len(images)} images but {len(labels)} labels")
    tiles = []
    for index, image in enumerate(images):
        array = np.asarray(image)
        if array.dtype != np.uint8:
            raise ValueError(f"image {index} must be uint8, got {array.dtype}")
        if array.ndim == 2:
            array = np.repeat(array[..., None], 3, axis=2)
        if array.ndim != 3 or array.shape[2] != 3:
            raise ValueError(f"image {index} must be [H, W] or [H, W, 3], got shape {list(array.shape)}")
        tiles.append(array)
    top = title_height if labels is not None else 0
    height = top + max(tile.shape[0] for tile in tiles)
    width = sum(tile.shape[1] for tile in tiles) + gap * (len(tiles) - 1)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    font = _font(max(8, title_height - 4))
    x = 0
    for index, tile in enumerate(tiles):
        cell = Image.new("RGB", (tile.shape[1], height), (255, 255, 255))
        cell.paste(Image.fromarray(tile), (0, top))
        if labels is not None:
            ImageDraw.Draw(cell).text((2, 1), str(labels[index]), fill=(0, 0, 0), font=font)
        canvas.paste(cell, (x, 0))
        x += tile.shape[1] + gap
    return np.asarray(canvas, dtype=np.uint8).copy()


def save_image(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write a uint8/uint16 ``[H, W]`` or ``[H, W, 3]`` picture as PNG atomically; returns the path."""
    return atomic_save_png(path, image)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def plot_training_curves(
    history: Sequence[Mapping[str, Any]],
    path: str | os.PathLike[str],
    step_key: str = "step",
    time_key: str = "seconds",
    loss_keys: Collection[str] | None = None,
) -> Path:
    """Chart every scalar series of a training history against step and against wall-clock time.

    Loss series share the top row (log scale when all values are positive); every other scalar gets one row per
    family (the part of its key before the first ``/``, e.g. ``psnr``, ``miou``), so series of different units
    never share an axis. Non-numeric, missing or non-finite values are skipped, so metrics logged only at some
    steps plot as sparse points joined by lines.

    Args:
        history: one mapping per logged step, each with ``step_key`` and optionally ``time_key`` (seconds since
            the start of training).
        path: PNG to write (atomically).
        step_key, time_key: names of the x-axis keys.
        loss_keys: keys plotted as losses; None means every key starting with ``loss``.

    Returns:
        ``path``.
    """
    steps: list[float] = []
    times: list[float | None] = []
    series: dict[str, list[tuple[int, float]]] = {}
    for index, record in enumerate(history):
        if step_key not in record or not _is_number(record[step_key]):
            raise ValueError(f"history entry {index} has no numeric '{step_key}'")
        steps.append(float(record[step_key]))
        time_value = record.get(time_key)
        times.append(float(time_value) if _is_number(time_value) else None)
        for key, value in record.items():
            if key not in (step_key, time_key) and _is_number(value):
                series.setdefault(key, []).append((index, float(value)))
    if not series:
        raise ValueError(f"history has no numeric series besides '{step_key}' and '{time_key}' to plot")
    if loss_keys is None:
        losses = [key for key in sorted(series) if key.startswith("loss")]
    else:
        losses = [key for key in sorted(series) if key in set(loss_keys)]
    families: dict[str, list[str]] = {}
    for key in sorted(series):
        if key not in losses:
            families.setdefault(key.split("/")[0], []).append(key)
    rows = ([losses] if losses else []) + list(families.values())
    axes_x = [(steps, "step")]
    if any(t is not None for t in times):
        axes_x.append((times, "wall-clock time (s)"))

    from matplotlib.backends.backend_agg import FigureCanvasAgg  # here: 0.4 s at every command's start otherwise
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6.0 * len(axes_x), 3.0 * len(rows)), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    for row, keys in enumerate(rows):
        for column, (xs, xlabel) in enumerate(axes_x):
            axis = figure.add_subplot(len(rows), len(axes_x), row * len(axes_x) + column + 1)
            for key in keys:
                points = [(xs[i], v) for i, v in series[key] if xs[i] is not None]
                if points:
                    xs_key, ys_key = zip(*points)
                    axis.plot(xs_key, ys_key, label=key, linewidth=1.2, marker=".", markersize=3)
            loss_row = keys is losses
            if loss_row and all(v > 0 for key in keys for _, v in series[key]):
                axis.set_yscale("log")
            axis.set_xlabel(xlabel)
            axis.set_ylabel("loss" if loss_row else keys[0].split("/")[0])
            axis.grid(True, alpha=0.3)
            if axis.get_legend_handles_labels()[0]:
                axis.legend(fontsize=7, loc="best")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return atomic_write_bytes(path, buffer.getvalue())
