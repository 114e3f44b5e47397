"""Registers the built-in view selectors."""

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.view_selectors.nearest import NearestViews, NearestViewsConfig


@hookimpl
def gpnerf_register_view_selectors() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "nearest",
            NearestViews,
            NearestViewsConfig,
            "nearest cameras by centre distance and viewing angle; random pick from a pool when training",
        )
    ]
