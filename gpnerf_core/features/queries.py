"""Queries against features: by example (a pixel or a box of one view), by embedding (a provider's text embedding, a
class prototype from labelled pixels), on any feature map ``[C, h, w]`` (a rendered feature field,
``Prediction.features``; GP-NeRF's rendered semantic embedding, ``Prediction.semantic``; a provider's own 2D map) and
any feature matrix ``[N, C]`` (per Gaussian, ``GaussianScene.feature_field`` or ``features``; per point).

Relevancy is the cosine similarity in [-1, 1] between each feature and the query: LERF's and LangSplat's relevancy
without their canonical negatives (a query by example needs no text to compare against). An example embedding or a
prototype is the mean of the L2-normalised features it covers (not normalised again: cosine ignores its norm).

Pixels are full-image pixel coordinates ``(x, y)`` (x to the right, y down, pixel centres at integers, as the datasets'
intrinsics have them); a feature map of stride ``s`` covers pixel ``(x, y)`` with cell ``(y // s, x // s)``, and an
``h x w`` map of an ``H x W`` image (a provider's grid need not divide the image: ``FeatureProvider.feature_size``
rounds) with cell ``(floor(y h / H), floor(x w / W))``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.geometry.gaussians.scene import GaussianScene
from gpnerf_core.runtime.ply import write_ply

EPS = 1e-8
"""Below this norm a feature counts as zero (its cosine with anything is 0)."""


def check_query_dimension(query: Tensor, channels: int, what: str = "the feature field") -> None:
    """Refuse a query embedding whose dimension is not the features' ``channels`` (one line naming both).

    Raises:
        ConfigError: ``query`` is not a vector of ``channels`` values.
    """
    if query.ndim != 1 or int(query.shape[0]) != int(channels):
        shape = "x".join(str(s) for s in query.shape) or "scalar"
        raise ConfigError(f"the query embedding has {shape} dimensions and {what} has {channels} channels; expected a "
                          f"query of {channels} values (an example, prototype or text embedding of the same features)")


def normalised(features: Tensor, dim: int) -> Tensor:
    """``features`` (float32) divided by their L2 norm along ``dim`` (zero features stay zero)."""
    values = features.float()
    return values / values.norm(dim=dim, keepdim=True).clamp_min(EPS)


def similarity_map(features: Tensor, query: Tensor) -> Tensor:
    """Cosine relevancy of every cell of ``features`` ``[C, h, w]`` to ``query`` ``[C]``: ``[h, w]`` float32 in
    [-1, 1].

    Raises:
        ConfigError: ``query`` of another dimension than ``C``.
    """
    if features.ndim != 3:
        raise ValueError(f"features must be a [C, h, w] map, got shape {list(features.shape)}")
    check_query_dimension(query, int(features.shape[0]))
    direction = normalised(query.to(features.device), dim=0)
    return torch.einsum("chw,c->hw", normalised(features, dim=0), direction)


def feature_stride(features: Tensor, image_size: tuple[int, int]) -> int:
    """Image pixels per feature cell of a ``[C, h, w]`` map of an ``(H, W)`` image (``H / h``, which must equal
    ``W / w``).

    Raises:
        ValueError: a grid that is not a whole division of the image.
    """
    height, width = int(features.shape[-2]), int(features.shape[-1])
    if image_size[0] % height or image_size[1] % width or image_size[0] // height != image_size[1] // width:
        raise ValueError(f"a {height}x{width} feature map does not divide the {image_size[0]}x{image_size[1]} image")
    return image_size[0] // height


def _cell(x: float, y: float, image: tuple[int, int], grid: tuple[int, int]) -> tuple[int, int]:
    if not (0 <= x < image[1] and 0 <= y < image[0]):
        raise ConfigError(f"query pixel ({x:g}, {y:g}) is outside the {image[0]}x{image[1]} image "
                          "(x in [0, width), y in [0, height))")
    return min(int(y * grid[0] // image[0]), grid[0] - 1), min(int(x * grid[1] // image[1]), grid[1] - 1)


def example_embedding(
    features: Tensor,
    *,
    pixel: tuple[float, float] | None = None,
    box: tuple[float, float, float, float] | None = None,
    stride: int = 1,
    image_size: tuple[int, int] | None = None,
) -> Tensor:
    """The query of an example in one view: ``[C]``, the mean of the normalised features of the cells the example
    covers.

    Args:
        features: ``[C, h, w]`` the view's feature map.
        pixel: ``(x, y)`` full-image pixel: the cell holding it.
        box: ``(x0, y0, x1, y1)`` full-image pixels, corners included: every cell holding a pixel of the box.
        stride: image pixels per feature cell (``feature_stride``).
        image_size: ``(H, W)`` of the image instead of ``stride``, for a grid that does not divide it.

    Raises:
        ConfigError: neither or both of ``pixel`` and ``box``, a pixel or a box outside the image, a box whose corners
            are not ordered.
    """
    if (pixel is None) == (box is None):
        raise ConfigError("a query example is a pixel (x, y) or a box (x0, y0, x1, y1); expected exactly one of them")
    grid = (int(features.shape[-2]), int(features.shape[-1]))
    image = tuple(image_size) if image_size is not None else (grid[0] * stride, grid[1] * stride)
    unit = normalised(features, dim=0)
    if pixel is not None:
        row, col = _cell(float(pixel[0]), float(pixel[1]), image, grid)
        return unit[:, row, col]
    x0, y0, x1, y1 = (float(v) for v in box)
    if x1 < x0 or y1 < y0:
        raise ConfigError(f"query box ({x0:g}, {y0:g}, {x1:g}, {y1:g}): expected x0 <= x1 and y0 <= y1")
    top, left = _cell(x0, y0, image, grid)
    bottom, right = _cell(x1, y1, image, grid)
    return unit[:, top:bottom + 1, left:right + 1].reshape(unit.shape[0], -1).mean(dim=1)


def cell_labels(labels: Tensor, grid: tuple[int, int], num_classes: int, ignore_index: int | None = None) -> Tensor:
    """Full-image labels ``[H, W]`` on a feature grid ``(h, w)``: each cell's most frequent label (``ignore_index``
    where the ignored pixels are the most frequent; a grid that does not divide the image takes the pixels under each
    cell as adaptive pooling does); ``[h, w]`` int64."""
    labels = labels.long()
    height, width = int(labels.shape[-2]), int(labels.shape[-1])
    if (height, width) == tuple(grid):
        return labels
    valid = (labels >= 0) & (labels < num_classes)
    buckets = torch.where(valid, labels, torch.full_like(labels, num_classes))  # the last bucket: ignored
    one_hot = F.one_hot(buckets, num_classes + 1).permute(2, 0, 1)[None].float()
    counts = F.adaptive_avg_pool2d(one_hot, tuple(grid))[0]
    cells = counts.argmax(dim=0)
    fill = ignore_index if ignore_index is not None else -1
    return torch.where(cells == num_classes, torch.full_like(cells, fill), cells)


def class_prototypes(
    features: Sequence[Tensor], labels: Sequence[Tensor], num_classes: int, ignore_index: int | None = None
) -> Tensor:
    """One prototype per class from labelled pixels: ``[K, C]``, the mean of the normalised features of the cells of
    class k over every map; a class with no labelled cell is a row of NaN (``nearest_prototype`` never picks it).

    Args:
        features: ``[C, h, w]`` maps (one channel count, any grids).
        labels: each map's labels, ``[h, w]`` or the full image ``[H, W]`` (``cell_labels`` puts them on the grid);
            values outside ``[0, K)`` (``ignore_index``) are not used.
    """
    if len(features) != len(labels):
        raise ValueError(f"{len(features)} feature maps and {len(labels)} label maps; expected one label map each")
    if not features:
        raise ValueError("class prototypes need at least one labelled feature map")
    channels = int(features[0].shape[0])
    sums = torch.zeros(num_classes, channels, dtype=torch.float64)
    counts = torch.zeros(num_classes, dtype=torch.float64)
    for feature, label in zip(features, labels):
        if int(feature.shape[0]) != channels:
            raise ConfigError(f"class prototypes: feature maps of {channels} and {int(feature.shape[0])} channels; "
                              "expected one feature space")
        grid = (int(feature.shape[-2]), int(feature.shape[-1]))
        cells = cell_labels(label.to(feature.device), grid, num_classes, ignore_index).reshape(-1).cpu()
        unit = normalised(feature, dim=0).reshape(channels, -1).T.double().cpu()
        keep = (cells >= 0) & (cells < num_classes)
        sums.index_add_(0, cells[keep], unit[keep])
        counts += torch.bincount(cells[keep], minlength=num_classes).double()
    prototypes = sums / counts[:, None].clamp_min(1)
    prototypes[counts == 0] = float("nan")
    return prototypes.float()


def nearest_prototype(features: Tensor, prototypes: Tensor) -> Tensor:
    """Each cell of ``features`` ``[C, h, w]`` labelled with the class of its most similar prototype (cosine; rows of
    NaN, classes without a prototype, are never chosen): ``[h, w]`` int64.

    Raises:
        ConfigError: prototypes of another dimension than ``C``; DataError: no class has a prototype.
    """
    present = torch.isfinite(prototypes).all(dim=1)
    if not bool(present.any()):
        raise DataError("nearest-prototype labels: no class has a prototype (no labelled pixel)")
    check_query_dimension(prototypes[0], int(features.shape[0]), "the feature map")
    unit = normalised(features, dim=0)
    rows = normalised(torch.nan_to_num(prototypes.to(unit.device)), dim=1)
    scores = torch.einsum("chw,kc->khw", unit, rows)
    scores[~present.to(scores.device)] = -float("inf")
    return scores.argmax(dim=0)


def text_embedding(provider: object, text: str) -> Tensor:
    """The query of a text: ``[C]``, the provider's text encoder's embedding of ``text``
    (``FeatureProvider.encode_text``, which refuses in one line a provider without one)."""
    if not text.strip():
        raise ConfigError("query text is empty; expected a word or a phrase")
    return provider.encode_text([text])[0].float()


def relevancy(feature_matrix: Tensor, query: Tensor) -> Tensor:
    """Cosine relevancy of every row of ``feature_matrix`` ``[N, C]`` (Gaussians, points) to ``query`` ``[C]``:
    ``[N]`` float32.

    Raises:
        ConfigError: ``query`` of another dimension than ``C``.
    """
    if feature_matrix.ndim != 2:
        raise ValueError(f"a feature matrix is [N, C], got shape {list(feature_matrix.shape)}")
    check_query_dimension(query, int(feature_matrix.shape[1]))
    return normalised(feature_matrix, dim=1) @ normalised(query.to(feature_matrix.device), dim=0)


def select_gaussians(feature_matrix: Tensor, query: Tensor, threshold: float) -> Tensor:
    """The rows (Gaussians, points) whose relevancy to ``query`` is at least ``threshold``: ``[N]`` bool.

    Raises:
        ConfigError: ``query`` of another dimension than the matrix's ``C``; a threshold outside [-1, 1].
    """
    if not -1.0 <= float(threshold) <= 1.0:
        raise ConfigError(f"query threshold {threshold!r}: expected a cosine similarity in [-1, 1]")
    return relevancy(feature_matrix, query) >= float(threshold)


def gaussian_feature_matrix(scene: GaussianScene) -> Tensor | None:
    """The per-Gaussian features a query is compared with: the distilled feature field (``feature_field``) where the
    scene has one, else the semantic features a head decodes (``features``); None without either."""
    field = getattr(scene, "feature_field", None)
    return field if field is not None else scene.features


def prediction_feature_map(prediction: object) -> Tensor | None:
    """The feature map of a prediction a query is compared with: the rendered feature field
    (``Prediction.features``) where the model has one, else the rendered semantic embedding (``semantic``)."""
    features = getattr(prediction, "features", None)
    return features if features is not None else getattr(prediction, "semantic", None)


def prediction_feature_source(prediction: object) -> str | None:
    """Which map ``prediction_feature_map`` takes: ``feature_field``, ``semantic_embedding`` or None."""
    if getattr(prediction, "features", None) is not None:
        return "feature_field"
    return "semantic_embedding" if getattr(prediction, "semantic", None) is not None else None


def write_gaussian_selection(
    path: str | os.PathLike[str], scene: GaussianScene, selected: Tensor, scores: Tensor | None = None,
    comments: tuple[str, ...] = (),
) -> Path:
    """The selected Gaussians as their own 3D Gaussian splatting PLY (the export's columns, ``GaussianScene.subset``),
    with each one's ``relevancy`` (float) when ``scores`` ``[G]`` are given; written atomically.

    Raises:
        DataError: no Gaussian is selected (an empty splat file opens as nothing in a viewer; lower the threshold).
    """
    chosen = selected.to(scene.means.device)
    if not bool(chosen.any()):
        raise DataError(f"query: none of the {scene.count} Gaussians is selected; nothing was written to {path} "
                        "(lower the threshold)")
    columns = scene.subset(chosen).ply_columns()
    if scores is not None:
        columns["relevancy"] = scores.to(chosen.device)[chosen].detach().to("cpu", torch.float32).numpy()
    return write_ply(path, columns, comments)


def write_point_selection(
    path: str | os.PathLike[str], xyz: Tensor, rgb: Tensor, selected: Tensor, scores: Tensor | None = None,
    comments: tuple[str, ...] = (),
) -> Path:
    """The selected points ``xyz`` ``[N, 3]`` (metres) with their colours ``rgb`` ``[N, 3]`` in [0, 1] as a PLY
    (``x y z red green blue`` and ``relevancy`` when ``scores`` are given), written atomically.

    Raises:
        DataError: no point is selected.
    """
    if not bool(selected.any()):
        raise DataError(f"query: none of the {int(xyz.shape[0])} points is selected; nothing was written to {path} "
                        "(lower the threshold)")
    keep = selected.cpu()
    points = xyz.detach().cpu()[keep].numpy().astype(np.float32)
    colours = (rgb.detach().float().cpu()[keep].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "red": colours[:, 0],
               "green": colours[:, 1], "blue": colours[:, 2]}
    if scores is not None:
        columns["relevancy"] = scores.detach().cpu()[keep].numpy().astype(np.float32)
    return write_ply(path, columns, comments)
