"""Weights into a model: one loader (``load_weights``) every path goes through, and ``model.init``'s start from another
run's or another code base's checkpoint (``init_weights``).

Every gpnerf-core checkpoint is checked as ``model.checkpoint.checked_state`` says (content hash included) and reaches
a model through ``load_weights``:
``eval``, ``render``, ``view``, ``stress``, ``finetune``, resuming and ``model.init``. ``load_weights`` refuses a
missing, extra or differently shaped tensor in one line; ``finetune`` on a dataset with another class count lets the
tensors whose first dimension is the class count keep their fresh initialisation (``new_classes``); ``model.init``
loads what the file provides and reports the rest (``partial``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError, DataError, NonFiniteError
from gpnerf_core.interfaces.model import ModelFamily
from gpnerf_core.model.checkpoint import checked_state, evaluation_weights, read_torch_file


def load_weights(
    module: torch.nn.Module,
    weights: Mapping[str, Tensor],
    source: str,
    *,
    partial: bool = False,
    new_classes: tuple[int, int] | None = None,
    explain: Callable[[], str] | None = None,
) -> list[str]:
    """Load ``weights`` into ``module``; returns the keys that kept their fresh initialisation for a new class count.

    Args:
        source: where the weights come from, for errors (``checkpoint <path>``, ``model.init=<path>``).
        partial: load the keys given, leave the module's others as they are (``model.init``); otherwise a missing or
            extra key is refused.
        new_classes: ``(checkpoint's, model's)`` class counts when they differ (``finetune`` on another dataset): a
            tensor whose first dimension is the class count in both and that matches otherwise keeps its
            initialisation.
        explain: what a shape mismatch is attributed to (the config keys that differ), for the error.

    Raises:
        DataError: a missing, extra (unless ``partial``) or differently shaped tensor, or one holding NaN or Inf, in
            one line.
        ConfigError: a differently shaped tensor when ``explain`` is given (the model config differs).
    """
    if isinstance(module, ModelFamily):
        module.hooks.check_weights(weights, source)  # a family refuses weights of a structure it no longer has
    if isinstance(module, ModelFamily) and module.capabilities.changes_size:
        module.hooks.resize_to(weights, source)  # a family that changes size takes the weights' sizes first
    own = module.state_dict()
    missing = [key for key in own if key not in weights] if not partial else []
    unexpected = [key for key in weights if key not in own]
    if missing or unexpected:
        detail = f"missing {missing[0]!r}" if missing else f"unexpected {unexpected[0]!r}"
        raise DataError(
            f"{source} does not match the configured model: {detail} "
            f"({len(missing)} missing, {len(unexpected)} unexpected tensors)"
        )
    reinitialised = []
    for key, value in weights.items():
        expected = tuple(own[key].shape)
        if tuple(value.shape) == expected:
            continue
        if new_classes is not None and _class_dimension(value.shape, expected, new_classes):
            reinitialised.append(key)
            continue
        found = f"tensor {key!r} has shape {list(value.shape)}, the configured model expects {list(expected)}"
        if explain is not None:
            raise ConfigError(f"{source}: {found}; the model config differs from the checkpoint's: {explain()}")
        raise DataError(f"{source}: {found} (a different model size?)")
    check_finite(weights, source, skip=reinitialised)
    loaded = {key: own[key] if key in reinitialised else value for key, value in weights.items()}
    module.load_state_dict(loaded, strict=not partial)
    return reinitialised


def check_finite(weights: Mapping[str, Tensor], source: str, skip: Sequence[str] = ()) -> None:
    """Refuse weights holding NaN or Inf, naming the first such tensor: loaded, they would surface only later as a
    non-finite loss or a blank picture, blamed on whatever read them first."""
    for key, value in weights.items():
        if key in skip or not (value.is_floating_point() or value.is_complex()):
            continue
        finite = torch.isfinite(value)
        if bool(finite.all()):
            continue
        nan = int(torch.isnan(value).sum())
        raise DataError(
            f"{source}: tensor {key!r} is not finite ({nan} NaN, {int((~finite).sum()) - nan} Inf of {value.numel()} "
            "values); the file's weights are damaged (saved from a diverged model?): use another checkpoint"
        )


def check_finite_model(model: torch.nn.Module, family: str, when: str) -> None:
    """Refuse to write ``model``'s weights when a floating tensor of its state dict holds NaN or Inf (the rule
    ``check_finite`` applies on loading, so a checkpoint written is one that loads): a ``NonFiniteError`` naming the
    family, the tensor and ``when`` (``step 40: checkpoint step_0000040.pt``). The trainer calls it before every
    checkpoint, so ``train.resume=auto`` finds the last finite one; the contract kit checks it sees a family's
    parameters."""
    found = non_finite_tensor(model)
    if found is not None:
        raise NonFiniteError(
            f"{when}: model {family!r} {found}, so it is not written; the newest checkpoint before it is finite "
            "(train.resume=auto resumes from it): lower the learning rates or find what diverged"
        )


def non_finite_tensor(model: torch.nn.Module) -> str | None:
    """``parameter 'x' holds NaN or Inf (3 of 600 values)`` for the first floating tensor of ``model``'s state dict
    that is not finite, or None."""
    for key, value in model.state_dict().items():
        if not (value.is_floating_point() or value.is_complex()):
            continue
        finite = torch.isfinite(value)
        if bool(finite.all()):
            continue
        kind = "parameter" if key in dict(model.named_parameters()) else "buffer"
        return f"{kind} {key!r} holds NaN or Inf ({int((~finite).sum())} of {value.numel()} values)"
    return None


def _class_dimension(found: torch.Size, expected: tuple[int, ...], classes: tuple[int, int]) -> bool:
    """The shapes differ only in a first dimension that is the class count (old in ``found``, new in ``expected``)."""
    old, new = classes
    return bool(found) and found[0] == old and expected[0] == new and tuple(found[1:]) == expected[1:]


@dataclass
class InitReport:
    """What ``init_weights`` did.

    Attributes:
        path, fmt: the file and its format (``gnt`` or ``gpnerf``).
        loaded: model keys loaded; missing: model keys the file does not provide (they keep their
            initialisation); unexpected: file keys no stage took; ignored: top-level entries left out on purpose.
    """

    path: Path
    fmt: str
    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        parts = [f"model.init={self.path} ({self.fmt}): loaded {len(self.loaded)} tensors"]
        if self.missing:
            parts.append(f"{len(self.missing)} keep their initialisation ({_groups(self.missing)})")
        if self.unexpected:
            parts.append(f"{len(self.unexpected)} in the file fit no parameter (first: {self.unexpected[0]})")
        if self.ignored:
            parts.append(f"ignored: {', '.join(self.ignored)}")
        return "; ".join(parts)


def _groups(keys: list[str], limit: int = 4) -> str:
    """``extractor.fpn.*, head.*`` from full keys: the first two name parts, in order of appearance."""
    seen = list(dict.fromkeys(".".join(key.split(".")[:2]) + ".*" for key in keys))
    return ", ".join(seen[:limit]) + (", ..." if len(seen) > limit else "")


def init_weights(model: ModelFamily, path: Path, *, strict: bool = True) -> InitReport:
    """Load the weights of ``path`` into ``model``.

    Args:
        strict: refuse a file holding keys no part takes (False: load the rest, report them).

    Raises:
        DataError: unreadable or damaged file (content hash, or a tensor holding NaN or Inf), a format the model does
            not read, a key no part takes (``strict``), or a tensor whose shape differs from the model's (always), each
            in one line naming ``model.init=<file>`` and the key.
    """
    if path.is_dir():
        raise DataError(f"model.init={path} is a folder; expected a file: a gpnerf-core checkpoint (e.g. "
                        f"<run>/checkpoints/step_XXXXXXX.pt) or weights {type(model).__name__} reads")
    if not path.is_file():
        raise DataError(f"model.init={path}: no such file; expected a gpnerf-core checkpoint or one model "
                        f"{type(model).__name__} reads")
    label = f"model.init={path}"
    checkpoint = read_torch_file(path, label)
    if not isinstance(checkpoint, Mapping):
        raise DataError(f"model.init={path}: holds a {type(checkpoint).__name__}, not a checkpoint dictionary")
    if "format" in checkpoint and "model" in checkpoint:
        report = InitReport(path=path, fmt="gpnerf")
        plan, offered = _gpnerf_plan(checked_state(dict(checkpoint), path, label))
    else:
        foreign = model.read_foreign(checkpoint)
        if foreign is None:
            raise DataError(f"model.init={path}: neither a gpnerf-core checkpoint nor a format model "
                            f"{type(model).__name__} reads; found {list(checkpoint)[:5]}")
        report = InitReport(path=path, fmt=foreign.format or "foreign", ignored=list(foreign.ignored))
        plan, offered = dict(foreign.tensors), list(foreign.offered)
    own = model.state_dict()
    taken = {source for key, (source, _) in plan.items() if key in own}
    report.unexpected = [source for key, (source, _) in plan.items() if key not in own]
    report.unexpected += [source for source in offered if source not in taken and source not in report.unexpected]
    if report.unexpected and strict:
        raise DataError(
            f"model.init={path}: key {report.unexpected[0]!r} fits no parameter of this model "
            f"({len(report.unexpected)} such keys); model.init_strict=false loads the rest"
        )
    loadable: dict[str, Tensor] = {}
    for key, (source, tensor) in plan.items():
        if key not in own:
            continue
        if tuple(tensor.shape) != tuple(own[key].shape):
            raise DataError(
                f"model.init={path}: {source!r} has shape {list(tensor.shape)} but {key!r} of this model has "
                f"{list(own[key].shape)} (a model of another size?)"
            )
        loadable[key] = tensor
    load_weights(model, loadable, label, partial=True)
    report.loaded = list(loadable)
    report.missing = [key for key in own if key not in loadable]
    return report


def _gpnerf_plan(state: Mapping[str, Any]) -> tuple[dict[str, tuple[str, Tensor]], list[str]]:
    """Another run's weights (its weight average where it kept one)."""
    weights, which = evaluation_weights(state)
    prefix = "weight_average.weights" if which == "average" else "model"
    plan = {key: (f"{prefix}.{key}", value) for key, value in weights.items()}
    return plan, [source for source, _ in plan.values()]
