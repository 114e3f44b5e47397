"""Built-in transformers: GNT's view transformer (FAT) and ray transformer (RAT)."""

from gpnerf_plugins.transformers.gnt_weights import GNTStateDicts, split_gnt_state_dict
from gpnerf_plugins.transformers.ray_transformer import GNTRayTransformer, GNTRayTransformerConfig
from gpnerf_plugins.transformers.view_transformer import (
    GNTViewContext,
    GNTViewTransformer,
    GNTViewTransformerConfig,
)

__all__ = [
    "GNTRayTransformer",
    "GNTRayTransformerConfig",
    "GNTStateDicts",
    "GNTViewContext",
    "GNTViewTransformer",
    "GNTViewTransformerConfig",
    "split_gnt_state_dict",
]
