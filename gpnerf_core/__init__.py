"""gpnerf-core: perception heads on generalizable NeRFs, assembled from pluggy plugins and Hydra configs."""

from gpnerf_core.hookspecs import hookimpl
from gpnerf_core.interfaces import (
    FeatureExtractor,
    FieldAggregator,
    LossSet,
    PerceptionHead,
    RayAggregator,
    SceneDataset,
    StressCase,
    ViewSelector,
)
from gpnerf_core.registry import get_registry
from gpnerf_core.specs import ComponentSpec, DataTool

__version__ = "0.1.0"

__all__ = [
    "ComponentSpec",
    "DataTool",
    "FeatureExtractor",
    "FieldAggregator",
    "LossSet",
    "PerceptionHead",
    "RayAggregator",
    "SceneDataset",
    "StressCase",
    "ViewSelector",
    "get_registry",
    "hookimpl",
]
