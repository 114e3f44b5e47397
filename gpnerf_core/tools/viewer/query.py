"""Queries in the viewer: a click on the view, a box dragged with shift held, or a text (where the feature provider
has a text encoder) becomes a query embedding, and every view shown afterwards carries its relevancy as a turbo colour map blended over the picture
where it reaches the threshold.

A query never renders: it reads the feature map of the view on screen (``RenderedView.prediction``: the rendered
feature field, else the semantic embedding) that the renderer kept, so answering costs one cosine per cell and one
picture (``answer``; ``tools/viewer/timing.py`` measures it)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.features.queries import (
    example_embedding, prediction_feature_map, similarity_map,
)
from gpnerf_core.types import Prediction

BLEND = 0.6
"""Weight of the colour map over the picture where the relevancy reaches the threshold."""


@dataclass(frozen=True, eq=False)
class Query:
    """What a client asked: the embedding ``[C]`` and how it was made (``pixel (x, y)`` or the text); two queries are
    equal only when they are the same query (the splats shown are keyed by it)."""

    embedding: torch.Tensor
    label: str


@dataclass(frozen=True)
class Answer:
    """One query on one view: the picture ``[H, W, 3]`` uint8 with the relevancy blended in, the share of the view's
    cells at or above the threshold, the highest relevancy, and the seconds it took (similarity and picture)."""

    picture: np.ndarray
    selected: float
    peak: float
    seconds: float


def view_features(prediction: Prediction | None) -> torch.Tensor:
    """The feature map ``[C, h, w]`` a query reads of a rendered view.

    Raises:
        ConfigError: no view yet, or a model that renders no feature map.
    """
    if prediction is None:
        raise ConfigError("no view is rendered yet to query")
    features = prediction_feature_map(prediction)
    if features is None:
        raise ConfigError("this model renders no feature map (neither a feature field nor a semantic embedding) to "
                          "query")
    return features


def image_size(prediction: Prediction) -> tuple[int, int]:
    """``(H, W)`` of the image a prediction renders (its grid times its stride)."""
    return int(prediction.rgb.shape[0]) * prediction.stride, int(prediction.rgb.shape[1]) * prediction.stride


def click_query(prediction: Prediction | None, screen_pos: tuple[float, float]) -> Query:
    """The query of a click at ``screen_pos`` (viser's: 0 to 1 from the top-left corner, the view filling the canvas):
    the feature of the clicked cell."""
    features = view_features(prediction)
    height, width = image_size(prediction)
    x = min(max(float(screen_pos[0]), 0.0), 1.0 - 1e-6) * width
    y = min(max(float(screen_pos[1]), 0.0), 1.0 - 1e-6) * height
    embedding = example_embedding(features.detach().float().cpu(), pixel=(x, y), image_size=(height, width))
    return Query(embedding=embedding, label=f"pixel ({x:.0f}, {y:.0f})")


def box_query(prediction: Prediction | None, screen_min: tuple[float, float],
              screen_max: tuple[float, float]) -> Query:
    """The query of a box dragged from ``screen_min`` to ``screen_max`` (viser's rectangle, 0 to 1 from the top-left):
    the mean of the normalised features of the cells it covers."""
    features = view_features(prediction)
    height, width = image_size(prediction)

    def pixel(value: float, size: int) -> float:
        return min(max(float(value), 0.0), 1.0 - 1e-6) * size

    x0, x1 = sorted((pixel(screen_min[0], width), pixel(screen_max[0], width)))
    y0, y1 = sorted((pixel(screen_min[1], height), pixel(screen_max[1], height)))
    embedding = example_embedding(features.detach().float().cpu(), box=(x0, y0, x1, y1), image_size=(height, width))
    return Query(embedding=embedding, label=f"box ({x0:.0f}, {y0:.0f})-({x1:.0f}, {y1:.0f})")


def relevancy_picture(picture: np.ndarray, similarity: torch.Tensor, threshold: float) -> np.ndarray:
    """``picture`` ``[H, W, 3]`` uint8 with the turbo colour map of ``similarity`` ``[h, w]`` (the threshold blue, 1
    red) blended in where it reaches ``threshold``; elsewhere the picture as it is."""
    size = picture.shape[:2]
    values = similarity.detach().float().cpu()[None, None]
    if tuple(values.shape[-2:]) != tuple(size):
        values = F.interpolate(values, size=size, mode="nearest")
    values = values[0, 0].numpy()
    span = max(1.0 - float(threshold), 1e-6)
    colours = vis._apply_colormap((values - float(threshold)) / span, "turbo").astype(np.float32)
    shown = values >= float(threshold)
    out = picture.astype(np.float32)
    out[shown] = (1 - BLEND) * out[shown] + BLEND * colours[shown]
    return out.round().clip(0, 255).astype(np.uint8)


def answer(prediction: Prediction | None, picture: np.ndarray, query: Query, threshold: float) -> Answer:
    """``query`` on the view ``prediction`` shown as ``picture`` (no render: the view's kept feature map).

    Raises:
        ConfigError: no feature map to read, or a query of another dimension than it (naming both).
    """
    began = time.perf_counter()
    similarity = similarity_map(view_features(prediction), query.embedding)
    blended = relevancy_picture(picture, similarity, threshold)
    return Answer(picture=blended, selected=float((similarity >= threshold).float().mean()),
                  peak=float(similarity.max()), seconds=time.perf_counter() - began)
