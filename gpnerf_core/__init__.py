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
from gpnerf_core.registry import ComponentSpec, DataTool, get_registry

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
