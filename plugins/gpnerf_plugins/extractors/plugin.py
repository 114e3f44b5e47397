"""Registers the built-in feature extractors."""

from __future__ import annotations

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.extractors.extractor import ResUNetFPN, ResUNetFPNConfig
from gpnerf_plugins.extractors.mvsnet import MVSNetFeatures, MVSNetFeaturesConfig


@hookimpl
def gpnerf_register_feature_extractors() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            name="resunet_fpn",
            factory=ResUNetFPN,
            config=ResUNetFPNConfig,
            description="GNT ResNet-34 U-Net (radiance, 1/4) + FPN (semantic, 4 levels at 1/2)",
        ),
        ComponentSpec(
            name="mvsnet",
            factory=MVSNetFeatures,
            config=MVSNetFeaturesConfig,
            description="MVSNeRF's FeatureNet: three conv blocks, BatchNorm + LeakyReLU, 32 channels at 1/4 (radiance)",
        ),
    ]
