"""A model's prediction as pictures: the one place evaluation, ``render`` and the viewer turn a ``Prediction`` into
images (``visualize`` draws them; this decides what a prediction shows).

Layers: ``rgb`` (clamped colours), ``depth`` (coloured between the scene's near and far), ``semantic`` (the argmax class
in the palette of ``visualize.label_palette``) or ``instances`` (each pixel's slot), and ``features`` (PCA of the
rendered semantic map). NaN or Inf show black: a picture never raises (the metrics refuse them).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, MutableMapping

import numpy as np
import torch
from torch import Tensor

from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.evaluation.instances import slot_predictions
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.interfaces.model import SemanticOutput
from gpnerf_core.types import Prediction


def rgb_picture(rgb: Tensor) -> np.ndarray:
    """``[h, w, 3]`` colours -> uint8, clamped to [0, 1] (NaN black, +Inf white)."""
    clean = torch.nan_to_num(rgb.detach().float().cpu(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0, 1)
    return (clean.numpy() * 255).round().astype(np.uint8)


def depth_picture(depth: Tensor, near: float, far: float) -> np.ndarray:
    """``[h, w]`` metres -> uint8, coloured linearly from ``near`` to ``far`` (unknown or non-finite depth black)."""
    return vis.depth_to_color(depth.detach().float().cpu(), near, far)


def predicted_classes(logits: Tensor) -> Tensor:
    """``[1, K, H, W]`` scores -> ``[H, W]`` int64 class ids (argmax; NaN scores count as 0)."""
    return torch.nan_to_num(logits[0].detach().float().cpu()).argmax(dim=0)


def score_layer(logits: Tensor, output: SemanticOutput, num_classes: int) -> tuple[str, np.ndarray]:
    """``("semantic", classes coloured)`` or ``("instances", slots coloured)`` of ``[1, K, H, W]`` scores."""
    if output.predicts is Predicts.INSTANCES:
        slots, _ = slot_predictions(torch.nan_to_num(logits[0].detach().float().cpu()), output.slot_activation)
        return "instances", vis.colorize_instances(slots)
    return "semantic", vis.colorize_labels(predicted_classes(logits), num_classes)


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Each pixel as a ``factor`` x ``factor`` block (a rendered cell shown at the image's size)."""
    return image if factor == 1 else image.repeat(factor, axis=0).repeat(factor, axis=1)


class Layers(MutableMapping[str, np.ndarray]):
    """Pictures by layer name, each drawn when first read (the viewer shows one layer of a frame: drawing every layer
    of every frame, a PCA among them, cost more than rendering a small frame); a layer set directly is kept as it is."""

    def __init__(self, draw: dict[str, Callable[[], np.ndarray]]) -> None:
        self._draw = dict(draw)
        self._drawn: dict[str, np.ndarray] = {}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._drawn:
            self._drawn[name] = self._draw[name]()
        return self._drawn[name]

    def __setitem__(self, name: str, picture: np.ndarray) -> None:
        self._draw[name] = lambda: picture
        self._drawn[name] = picture

    def __delitem__(self, name: str) -> None:
        del self._draw[name]
        self._drawn.pop(name, None)

    def __iter__(self) -> Iterator[str]:
        return iter(self._draw)

    def __len__(self) -> int:
        return len(self._draw)


def prediction_layers(
    prediction: Prediction,
    near: float,
    far: float,
    output: SemanticOutput | None,
    num_classes: int,
    *,
    full_size: bool = False,
) -> Layers:
    """The pictures of one prediction by layer name (``rgb``, ``depth``, ``semantic`` or ``instances``, ``features``),
    each drawn when first read.

    Args:
        output: the model's ``semantic_output`` (None: no score layer).
        num_classes: the palette's size for ``semantic``.
        full_size: show the rendered grid at the image's size (each cell a block of ``prediction.stride`` pixels);
            otherwise ``rgb``, ``depth`` and ``features`` are at the grid's size (the score layer always is at the
            image's).
    """
    factor = prediction.stride if full_size else 1
    draw: dict[str, Callable[[], np.ndarray]] = {
        "rgb": lambda: upscale(rgb_picture(prediction.rgb), factor),
        "depth": lambda: upscale(depth_picture(torch.nan_to_num(prediction.depth.float()), near, far), factor),
    }
    if prediction.logits is not None and output is not None:
        name = "instances" if output.predicts is Predicts.INSTANCES else "semantic"
        draw[name] = lambda: score_layer(prediction.logits, output, num_classes)[1]
    if prediction.semantic is not None:
        draw["features"] = lambda: upscale(vis.pca_rgb(torch.nan_to_num(prediction.semantic.detach().float().cpu())),
                                           factor)
    return Layers(draw)
