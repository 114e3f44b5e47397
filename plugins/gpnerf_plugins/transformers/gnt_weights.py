"""Map a GNT (or GP-NeRF) ``net_coarse`` state dict onto ``gnt_view`` and ``gnt_ray``.

An official GNT checkpoint (``torch.save`` by GNT's ``GNTModel.save_model``) is a dict with ``net_coarse`` (the
transformer), ``feature_net`` (the ResUNet), optionally ``net_fine``, and the optimizer and scheduler states.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from torch import Tensor

from gpnerf_core import ImportedWeights

# GNT checkpoint prefix -> (target, prefix in our module). GNT renamed its block lists between versions:
# ``view_crosstrans``/``view_selftrans`` (released checkpoints, GP-NeRF) and ``view_trans``/``ray_trans``.
_PREFIXES: tuple[tuple[str, str, str], ...] = (
    ("rgbfeat_fc.", "field", "rgbfeat_fc."),
    ("q_fcs.", "field", "q_fcs."),
    ("view_crosstrans.", "field", "blocks."),
    ("view_trans.", "field", "blocks."),
    ("view_selftrans.", "ray", "blocks."),
    ("ray_trans.", "ray", "blocks."),
    ("norm.", "ray", "norm."),
    ("rgb_fc.", "ray", "rgb_fc."),
)


@dataclass(frozen=True)
class GNTStateDicts:
    """A GNT transformer state dict split by destination.

    Attributes:
        field: keys for ``GNTViewTransformer.load_state_dict``.
        ray: keys for ``GNTRayTransformer.load_state_dict``.
        unused: everything else (e.g. GP-NeRF's ``semantic_adaptor``), under its original key.
    """

    field: dict[str, Tensor]
    ray: dict[str, Tensor]
    unused: dict[str, Tensor]


def route_gnt_key(key: str) -> tuple[str, str] | None:
    """``(target, key in our module)`` for a GNT transformer key (a leading ``module.`` from DDP is dropped);
    None for a key neither aggregator has (e.g. GP-NeRF's ``semantic_adaptor``)."""
    name = key.removeprefix("module.")
    for prefix, target, ours in _PREFIXES:
        if name.startswith(prefix):
            return target, ours + name[len(prefix) :]
    return None


def split_gnt_state_dict(state_dict: dict[str, Tensor]) -> GNTStateDicts:
    """Route every key of a GNT transformer state dict."""
    parts: dict[str, dict[str, Tensor]] = {"field": {}, "ray": {}}
    unused: dict[str, Tensor] = {}
    for key, value in state_dict.items():
        route = route_gnt_key(key)
        if route is None:
            unused[key] = value
        else:
            parts[route[0]][route[1]] = value
    return GNTStateDicts(field=parts["field"], ray=parts["ray"], unused=unused)


def import_gnt_transformer(checkpoint: Mapping[str, Any], target: str) -> ImportedWeights | None:
    """The ``field`` or ``ray`` share of an official GNT checkpoint's ``net_coarse`` (None without one)."""
    state = checkpoint.get("net_coarse")
    if not isinstance(state, Mapping):
        return None
    tensors = {}
    for key, value in state.items():
        route = route_gnt_key(key)
        if route is not None and route[0] == target:
            tensors[route[1]] = (f"net_coarse.{key}", value)
    return ImportedWeights(tensors)
