"""Checks on what a component returns, where it returns it: a head's logits of the wrong shape, or a head's or feature
extractor's output holding NaN or Inf, stop the run in one line naming the component and the plugin behind it, instead
of surfacing later as a loss term (``loss term 'ce' is nan``) or a class's shape error.

Installed on the components a pipeline builds (``model.build.ConfiguredParts``) as forward hooks: one ``isfinite().all()``
per output tensor; the inputs are looked at only once an output is found non-finite, to say whose fault it is. The
contract kit (``gpnerf_core.testing``) builds components without them, so its own checks report what it finds.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gpnerf_core.errors import NonFiniteError, PluginError
from gpnerf_core.types import FeatureMaps, HeadOutput
from gpnerf_core.runtime.finite import all_finite

GUARDED_KINDS = ("head", "feature_extractor")
"""The kinds whose outputs are checked (each a module called once per view, through ``forward``)."""


def guard_outputs(kind: str, component: Any, where: str, upstream: str | None = None) -> None:
    """Check every output of ``component`` (a built ``kind``; ``where`` names it and its plugin, for errors;
    ``upstream`` names what makes its input, the model family and its plugin, blamed when that input is not finite)."""
    if not isinstance(component, torch.nn.Module):
        return
    if kind == "head":
        component.register_forward_hook(_head_hook(where, upstream), with_kwargs=True)
    elif kind == "feature_extractor":
        component.register_forward_hook(_extractor_hook(where), with_kwargs=True)


def _argument(args: tuple[Any, ...], kwargs: dict[str, Any], index: int, name: str) -> Any:
    return args[index] if len(args) > index else kwargs.get(name)


def _head_hook(where: str, upstream: str | None = None) -> Any:
    def check(module: Any, args: tuple[Any, ...], kwargs: dict[str, Any], output: Any) -> None:
        features = _argument(args, kwargs, 0, "features")
        size = _argument(args, kwargs, 1, "output_size")
        logits = getattr(output, "logits", None)
        if isinstance(features, Tensor) and size is not None:
            expected = [int(features.shape[0]), int(module.num_outputs), int(size[0]), int(size[1])]
            if not isinstance(output, HeadOutput) or not isinstance(logits, Tensor) or list(logits.shape) != expected:
                found = f"logits {list(logits.shape)}" if isinstance(logits, Tensor) else f"a {type(output).__name__}"
                raise PluginError(
                    f"{where} returned {found}; the PerceptionHead contract is "
                    f"HeadOutput(logits=[N, num_outputs, *output_size]) = {expected} for features "
                    f"{list(features.shape)} and output_size {tuple(size)}"
                )
        if isinstance(logits, Tensor) and not all_finite(logits):
            raise NonFiniteError(f"{where} returned logits that are not finite ({_count(logits)}) "
                                 f"{_inputs_note(features, 'features', upstream)}")

    return check


def _extractor_hook(where: str) -> Any:
    def check(module: Any, args: tuple[Any, ...], kwargs: dict[str, Any], output: Any) -> None:
        if not isinstance(output, FeatureMaps):
            return
        for name in ("radiance", "semantic"):
            maps = getattr(output, name)
            if isinstance(maps, Tensor) and not all_finite(maps):
                images = _argument(args, kwargs, 0, "images")
                raise NonFiniteError(f"{where} returned {name} feature maps that are not finite ({_count(maps)}) "
                                     f"{_inputs_note(images, 'images')}")

    return check


def _count(values: Tensor) -> str:
    """``3 NaN, 0 Inf of 4096 values``."""
    nan = int(torch.isnan(values).sum())
    inf = int(torch.isinf(values).sum())
    return f"{nan} NaN, {inf} Inf of {values.numel()} values"


def _inputs_note(inputs: Any, name: str, upstream: str | None = None) -> str:
    """Whose fault: the component's (its input was finite) or what fed it (``upstream``, when known)."""
    if isinstance(inputs, Tensor) and not all_finite(inputs):
        culprit = f", in {upstream}, which made them" if upstream else ""
        return (f"from input {name} that were not finite already ({_count(inputs)}): the fault is upstream of it"
                f"{culprit}")
    return f"from finite input {name}"
