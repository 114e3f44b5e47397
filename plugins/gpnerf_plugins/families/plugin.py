"""Registers the built-in model families."""

from __future__ import annotations

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.families.gnt.build import build_gnt
from gpnerf_plugins.families.gnt.config import GNTModelConfig


@hookimpl
def gpnerf_register_models() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "gnt",
            build_gnt,
            GNTModelConfig,
            "GNT view + ray transformers over source views; GP-NeRF's semantic field on their attention, +head decodes",
        ),
    ]
