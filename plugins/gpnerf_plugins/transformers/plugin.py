"""Registers GNT's view transformer (``gnt_view``) and ray transformer (``gnt_ray``)."""

from __future__ import annotations

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.transformers.ray_transformer import GNTRayTransformer, GNTRayTransformerConfig
from gpnerf_plugins.transformers.view_transformer import GNTViewTransformer, GNTViewTransformerConfig


@hookimpl
def gpnerf_register_field_aggregators() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "gnt_view",
            GNTViewTransformer,
            GNTViewTransformerConfig,
            "GNT view transformer (GP-NeRF FAT): per-channel subtraction attention over source views",
        )
    ]


@hookimpl
def gpnerf_register_ray_aggregators() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "gnt_ray",
            GNTRayTransformer,
            GNTRayTransformerConfig,
            "GNT ray transformer (GP-NeRF RAT): multi-head self-attention along each ray, unbounded RGB readout",
        )
    ]
