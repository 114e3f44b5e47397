"""What a model family's training forward must give, checked on every step of ``run`` and ``finetune`` (as the heads'
and extractors' outputs are checked where they are made, ``registry.guards``): the shapes of the contract
(``ModelFamily.forward``), the semantic outputs its ``semantic_output`` promises, and finite values, so a family that
returns depth ``[R, 1]`` or NaN colour stops the run in one line naming it and its plugin instead of training on.

The contract kit (``gpnerf_core.testing``) checks the same shapes on its synthetic scene; this is the run's own check,
on the data it trains on. The values are looked at with one ``isfinite().all()`` per output tensor.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from gpnerf_core.errors import ConfigError, NonFiniteError, PluginError
from gpnerf_core.interfaces.model import ModelFamily, SemanticMode, TrainingBatch
from gpnerf_core.runtime.finite import all_finite
from gpnerf_core.types import ImageOutput, RenderedRays, StepBatch, StepOutput, TargetView, ViewOutput


def _shape(value: Any) -> str:
    return str(list(value.shape)) if isinstance(value, Tensor) else type(value).__name__


def _expect(value: Any, expected: list[int | None], what: str, where: str) -> None:
    """``value`` is a tensor of ``expected`` shape (None: any size on that axis)."""
    if not isinstance(value, Tensor) or value.dim() != len(expected) or any(
            size is not None and int(actual) != size for actual, size in zip(value.shape, expected)):
        shown = "[" + ", ".join("*" if size is None else str(size) for size in expected) + "]"
        raise PluginError(f"{where} returned {what} {_shape(value)}; the ModelFamily contract is {shown} (forward)")


def _check_pass(name: str, rendered: Any, rays: int, classes: int | None, where: str) -> None:
    if not isinstance(rendered, RenderedRays):
        raise PluginError(f"{where} returned {name} as a {type(rendered).__name__}; the ModelFamily contract is "
                          "RenderedRays (forward)")
    _expect(rendered.rgb, [rays, 3], f"{name}.rgb", where)
    _expect(rendered.depth, [rays], f"{name}.depth", where)
    if rendered.weights is not None:
        _expect(rendered.weights, [rays, None], f"{name}.weights", where)
    if rendered.semantic is not None:
        _expect(rendered.semantic, [rays, None], f"{name}.semantic", where)
    if rendered.logits is not None:
        _expect(rendered.logits, [rays, classes], f"{name}.logits", where)
    for field in ("rgb", "depth", "semantic", "sample_semantic", "logits"):
        value = getattr(rendered, field)
        if isinstance(value, Tensor) and value.is_floating_point() and not all_finite(value.detach()):
            raise NonFiniteError(f"{where} rendered {name}.{field} that is not finite (NaN or Inf)")


def check_image_output(model: ModelFamily, view: TargetView, output: Any, semantics: bool, where: str) -> None:
    """One target view's ``ImageOutput`` (a family that trains on whole images) against the contract."""
    if not isinstance(output, ImageOutput):
        raise PluginError(f"{where} returned a {type(output).__name__} per view; a family that trains on whole images "
                          "(Capabilities.trains_on = TrainingBatch.IMAGES) returns ImageOutput (forward)")
    semantic = model.semantic_output
    classes = semantic.num_outputs if semantic is not None else None
    height, width = view.camera.image_size
    _expect(output.rgb, [height, width, 3], "image rgb", where)
    _expect(output.depth, [height, width], "image depth", where)
    if output.alpha is not None:
        _expect(output.alpha, [height, width], "image alpha", where)
    for name in ("scores", "logits"):
        if getattr(output, name) is not None:
            _expect(getattr(output, name), [1, classes, height, width], f"image {name}", where)
    for name in ("semantic", "teacher_map"):
        if getattr(output, name) is not None:
            _expect(getattr(output, name), [1, None, None, None], f"image {name}", where)
    for name in ("rgb", "depth", "alpha", "scores", "semantic", "teacher_map", "logits"):
        value = getattr(output, name)
        if isinstance(value, Tensor) and value.is_floating_point() and not all_finite(value.detach()):
            raise NonFiniteError(f"{where} rendered image {name} that is not finite (NaN or Inf)")
    if not semantics or semantic is None:
        return
    if semantic.mode is SemanticMode.DECODED and output.logits is None:
        raise ConfigError(f"{where} says its semantic output is decoded by a head (SemanticMode.DECODED) but its "
                          "forward(semantics=True) gave no logits: it ignores its head")
    if semantic.mode is SemanticMode.LABEL_RENDERING and output.scores is None:
        raise ConfigError(f"{where} says it renders labels (SemanticMode.LABEL_RENDERING) but its "
                          "forward(semantics=True) gave no per-pixel scores")


def check_view_output(model: ModelFamily, view: TargetView, output: Any, semantics: bool, where: str) -> None:
    """One target view's output against the contract: a ``ViewOutput`` of rays, or the ``ImageOutput`` of a family
    that trains on whole images; ``where`` names the family and its plugin."""
    if model.capabilities.trains_on is TrainingBatch.IMAGES:
        check_image_output(model, view, output, semantics, where)
        return
    if not isinstance(output, ViewOutput):
        raise PluginError(f"{where} returned a {type(output).__name__} per view; the ModelFamily contract is "
                          "ViewOutput (forward)")
    semantic = model.semantic_output
    classes = semantic.num_outputs if semantic is not None else None
    rays = view.num_rays
    _check_pass("coarse", output.coarse, rays, classes, where)
    if output.fine is not None:
        _check_pass("fine", output.fine, rays, classes, where)
    if output.logits is not None:
        _expect(output.logits, [1, classes, view.camera.height, view.camera.width], "logits", where)
    if not semantics or semantic is None:
        return
    if semantic.mode is SemanticMode.DECODED and output.logits is None:
        raise ConfigError(f"{where} says its semantic output is decoded by a head (SemanticMode.DECODED) but its "
                          "forward(semantics=True) gave no logits: it ignores its head")
    if semantic.mode is SemanticMode.LABEL_RENDERING and output.last.logits is None:
        raise ConfigError(f"{where} says it renders labels (SemanticMode.LABEL_RENDERING) but its "
                          "forward(semantics=True) gave no per-ray logits")


def check_step_output(model: ModelFamily, batch: StepBatch, output: Any, semantics: bool, where: str) -> None:
    """A training forward's ``StepOutput``: one ``ViewOutput`` per target view, each as ``check_view_output``."""
    views = getattr(output, "views", None)
    if not isinstance(output, StepOutput) or not isinstance(views, tuple) or len(views) != len(batch.views):
        found = f"{len(views)} views" if isinstance(views, tuple) else type(output).__name__
        raise PluginError(f"{where} returned {found} for a batch of {len(batch.views)} target views; the ModelFamily "
                          "contract is a StepOutput with one output per target view (forward)")
    for view, view_output in zip(batch.views, views):
        check_view_output(model, view, view_output, semantics, where)
