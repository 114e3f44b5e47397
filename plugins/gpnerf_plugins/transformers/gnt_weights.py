"""Map a GNT (or GP-NeRF) ``net_coarse`` state dict onto ``gnt_view`` and ``gnt_ray``."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

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


def split_gnt_state_dict(state_dict: dict[str, Tensor]) -> GNTStateDicts:
    """Route every key of a GNT transformer state dict (a leading ``module.`` from DDP is dropped)."""
    parts: dict[str, dict[str, Tensor]] = {"field": {}, "ray": {}}
    unused: dict[str, Tensor] = {}
    for key, value in state_dict.items():
        name = key.removeprefix("module.")
        for prefix, target, ours in _PREFIXES:
            if name.startswith(prefix):
                parts[target][ours + name[len(prefix) :]] = value
                break
        else:
            unused[key] = value
    return GNTStateDicts(field=parts["field"], ray=parts["ray"], unused=unused)
