"""Reading an official GNT checkpoint into the ``gnt`` family (``model.init=<GNT model_*.pth>``).

GP-NeRF's README recommends starting from GNT's pretrained weights. A GNT checkpoint holds ``net_coarse`` (the view and
ray transformers), ``feature_net`` (the ResUNet), optionally ``net_fine``, and its optimizer and scheduler states. Each
stage maps its share through ``import_weights`` (``ImportsWeights``); GP-NeRF's ``semantic_adaptor`` goes onto the
semantic field's adaptor. The core checks every name and shape, loads, and reports.
"""

from __future__ import annotations

from typing import Any, Mapping

from torch import nn

from gpnerf_core import ImportedWeights

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
STAGES = ("extractor", "field", "ray", "head")
"""The model's stages (attribute names) asked for their share."""


def is_gnt_checkpoint(checkpoint: Mapping[str, Any]) -> bool:
    return any(key in checkpoint for key in GNT_WEIGHTS)


def read_gnt_checkpoint(model: nn.Module, checkpoint: Mapping[str, Any]) -> ImportedWeights | None:
    """The model's tensors from a GNT checkpoint, by the model's state-dict keys; None for another format."""
    if not is_gnt_checkpoint(checkpoint):
        return None
    tensors = {}
    for prefix in STAGES:
        component = getattr(model, prefix, None)
        imported = component.import_weights(checkpoint, "gnt") if component is not None else None
        if imported is not None:
            tensors.update({f"{prefix}.{key}": entry for key, entry in imported.tensors.items()})
    offered, ignored = [], []
    for top, entries in checkpoint.items():
        if top in GNT_IGNORED:
            ignored.append(top)
        elif top in GNT_WEIGHTS and isinstance(entries, Mapping):
            offered += [f"{top}.{key}" for key in entries]
        else:
            offered.append(top)
    if getattr(model, "semantic", None) is not None:
        for source, key in ADAPTOR_KEYS.items():
            top, _, rest = source.partition(".")
            value = checkpoint.get(top, {}).get(rest) if isinstance(checkpoint.get(top), Mapping) else None
            if value is not None:
                tensors[key] = (source, value)
    return ImportedWeights(tensors, format="gnt", offered=tuple(offered), ignored=tuple(ignored))
