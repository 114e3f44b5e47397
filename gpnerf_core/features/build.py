"""The feature provider a composed config selects (``+feature_provider=<name>``), built through the registry."""

from __future__ import annotations

from typing import Any

from gpnerf_core.interfaces.feature_provider import FeatureProvider
from gpnerf_core.registry.components import Registry, get_registry
from gpnerf_core.registry.kinds import section


def build_feature_provider(cfg: Any, registry: Registry | None = None) -> FeatureProvider | None:
    """The provider of ``cfg``'s ``feature_provider`` section (a composed config, or plain dicts), built with its
    options; None when the config selects none.

    Raises:
        ConfigError: an unknown provider name (the message lists the known ones), an option it does not have, or a
            package or weights file it needs that is missing (naming the path and the extra to install).
    """
    node = section(cfg, "feature_provider")
    if node is None:
        return None
    return (registry or get_registry()).build("feature_provider", node)
