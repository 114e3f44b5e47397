"""``model.init``: start a model from an official GNT checkpoint, or from a gpnerf-core checkpoint's weights.

GP-NeRF's README recommends starting from GNT's pretrained weights. A GNT checkpoint holds ``net_coarse`` (the
view and ray transformers), ``feature_net`` (the ResUNet), optionally ``net_fine``, and its optimizer and scheduler
states. Each model stage maps its share through ``import_weights`` (see ``gpnerf_core.interfaces.weights``); the
core maps GP-NeRF's ``semantic_adaptor`` onto the semantic field's adaptor, checks every name and shape, loads, and
reports what was loaded, what kept its initialisation and what no stage took.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from torch import Tensor

from gpnerf_core.errors import DataError
from gpnerf_core.model.pipeline import GeneralizableNeRF
from gpnerf_core.model.checkpoint import FORMAT_VERSION, evaluation_weights, read_torch_file

GNT_WEIGHTS = ("net_coarse", "feature_net")
GNT_IGNORED = ("optimizer", "scheduler", "net_fine")
"""Training state, and GNT's separate fine network (this model renders both passes with one network, as GNT's
``single_net``)."""

ADAPTOR_KEYS = {
    "net_coarse.semantic_adaptor.weight": "semantic.adaptor.weight",
    "net_coarse.semantic_adaptor.bias": "semantic.adaptor.bias",
    "net_coarse.semantic_adaptor.0.weight": "semantic.adaptor.weight",
    "net_coarse.semantic_adaptor.0.bias": "semantic.adaptor.bias",
}


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


def detect_format(checkpoint: Any, path: Path) -> str:
    if isinstance(checkpoint, Mapping) and "format" in checkpoint and "model" in checkpoint:
        return "gpnerf"
    if isinstance(checkpoint, Mapping) and any(key in checkpoint for key in GNT_WEIGHTS):
        return "gnt"
    found = list(checkpoint)[:5] if isinstance(checkpoint, Mapping) else type(checkpoint).__name__
    raise DataError(
        f"model.init={path}: neither an official GNT checkpoint (net_coarse, feature_net) nor a gpnerf-core "
        f"checkpoint; found {found}"
    )


def init_weights(model: GeneralizableNeRF, path: Path, *, strict: bool = True) -> InitReport:
    """Load the weights of ``path`` into ``model``.

    Args:
        strict: refuse a file holding keys no stage takes (False: load the rest, report them).

    Raises:
        DataError: unreadable file, unknown format, a key no stage takes (``strict``), or a tensor whose shape
            differs from the model's (always), each in one line naming the file and the key.
    """
    if not path.is_file():
        raise DataError(f"model.init={path}: no such file; expected an official GNT checkpoint or a gpnerf-core one")
    checkpoint = read_torch_file(path)
    fmt = detect_format(checkpoint, path)
    report = InitReport(path=path, fmt=fmt)
    plan, offered = _gpnerf_plan(checkpoint, path) if fmt == "gpnerf" else _gnt_plan(model, checkpoint, report)
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
    model.load_state_dict(loadable, strict=False)
    report.loaded = list(loadable)
    report.missing = [key for key in own if key not in loadable]
    return report


def _gpnerf_plan(checkpoint: Mapping[str, Any], path: Path) -> tuple[dict[str, tuple[str, Tensor]], list[str]]:
    if checkpoint["format"] != FORMAT_VERSION:
        raise DataError(
            f"model.init={path}: gpnerf-core checkpoint format {checkpoint['format']!r}; expected {FORMAT_VERSION}"
        )
    weights, which = evaluation_weights(checkpoint)
    prefix = "weight_average.weights" if which == "average" else "model"
    plan = {key: (f"{prefix}.{key}", value) for key, value in weights.items()}
    return plan, [source for source, _ in plan.values()]


def _gnt_plan(
    model: GeneralizableNeRF, checkpoint: Mapping[str, Any], report: InitReport
) -> tuple[dict[str, tuple[str, Tensor]], list[str]]:
    plan: dict[str, tuple[str, Tensor]] = {}
    for prefix in ("extractor", "field", "ray", "head"):
        component = getattr(model, prefix)
        imported = component.import_weights(checkpoint, "gnt") if component is not None else None
        if imported is not None:
            plan.update({f"{prefix}.{key}": entry for key, entry in imported.tensors.items()})
    offered = []
    for top, entries in checkpoint.items():
        if top in GNT_IGNORED:
            report.ignored.append(top)
        elif top in GNT_WEIGHTS and isinstance(entries, Mapping):
            offered += [f"{top}.{key}" for key in entries]
        else:
            offered.append(top)
    if model.semantic is not None:
        for source, key in ADAPTOR_KEYS.items():
            top, _, rest = source.partition(".")
            value = checkpoint.get(top, {}).get(rest) if isinstance(checkpoint.get(top), Mapping) else None
            if value is not None:
                plan[key] = (source, value)
    return plan, offered
