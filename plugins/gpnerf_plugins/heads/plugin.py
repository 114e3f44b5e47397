"""Registers the built-in perception heads."""

from __future__ import annotations

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.heads.instance import InstanceHead, InstanceHeadConfig
from gpnerf_plugins.heads.per_pixel import PerPixelHead, PerPixelHeadConfig
from gpnerf_plugins.heads.unet import UNetHead, UNetHeadConfig


@hookimpl
def gpnerf_register_heads() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            name="unet",
            factory=UNetHead,
            config=UNetHeadConfig,
            description="GP-NeRF context-aware decoder over the 4 semantic levels (U-Net or Semantic-FPN form)",
        ),
        ComponentSpec(
            name="per_pixel",
            factory=PerPixelHead,
            config=PerPixelHeadConfig,
            description="per-pixel MLP, no spatial context (label-rendering baseline)",
        ),
        ComponentSpec(
            name="instance",
            factory=InstanceHead,
            config=InstanceHeadConfig,
            description="context-aware decoder with slots + 1 instance outputs (Hungarian loss: +loss=instance)",
        ),
    ]
