"""The contract checks of each component kind: ``CHECKS[kind]`` maps a check's name to ``check(subject)``.

A check raises ``CheckFailed`` with the shapes involved when the component breaks the rule, ``CheckSkipped`` when it
cannot run here. ``RUNTIME[kind]`` holds the keyword arguments the kit passes in the pipeline's place.
"""

from __future__ import annotations

from typing import Any, Callable

from gpnerf_core.testing import inputs
from gpnerf_core.testing.checks import (
    aggregators, datasets, depth_sources, extractors, feature_providers, heads, losses, models, selectors,
)
from gpnerf_core.testing.checks.common import CheckFailed, CheckSkipped, Subject

CHECKS: dict[str, dict[str, Callable[[Subject], None]]] = {
    "model": models.CHECKS,
    "feature_extractor": extractors.CHECKS,
    "field_aggregator": aggregators.FIELD_CHECKS,
    "ray_aggregator": aggregators.RAY_CHECKS,
    "head": heads.CHECKS,
    "loss": losses.CHECKS,
    "dataset": datasets.CHECKS,
    "view_selector": selectors.CHECKS,
    "depth_source": depth_sources.CHECKS,
    "feature_provider": feature_providers.CHECKS,
}

RUNTIME: dict[str, dict[str, Any]] = {
    "model": {},  # ``parts``: the parts its config declares (``inputs.kit_parts``), made per check
    "feature_extractor": {},
    "field_aggregator": {"in_dim": inputs.FIELD_IN_DIM},
    "ray_aggregator": {"in_dim": inputs.RAY_IN_DIM, "num_blocks": inputs.RAY_BLOCKS},
    "head": {"in_dim": inputs.HEAD_IN_DIM, "in_levels": inputs.HEAD_LEVELS, "num_outputs": 3},
    "loss": {},
    "dataset": {},
    "view_selector": {},
    "depth_source": {},
    "feature_provider": {},
}

__all__ = ["CHECKS", "RUNTIME", "CheckFailed", "CheckSkipped", "Subject"]
