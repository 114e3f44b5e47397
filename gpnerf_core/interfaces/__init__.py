"""Abstract interfaces of every pluggable component kind (the dataset interface is ``gpnerf_core.data.dataset``, beside
the dataset base)."""

from gpnerf_core.interfaces.depth_source import DepthSource
from gpnerf_core.interfaces.feature_extractor import FeatureExtractor
from gpnerf_core.interfaces.feature_provider import FeatureProvider
from gpnerf_core.interfaces.field_aggregator import FieldAggregator
from gpnerf_core.interfaces.head import PerceptionHead
from gpnerf_core.interfaces.loss import LossSet
from gpnerf_core.interfaces.model import ModelFamily
from gpnerf_core.interfaces.ray_aggregator import RayAggregator
from gpnerf_core.interfaces.stress import StressCase
from gpnerf_core.interfaces.view_selector import ViewSelector
from gpnerf_core.interfaces.weights import ImportedWeights, ImportsWeights

__all__ = [
    "DepthSource",
    "FeatureExtractor",
    "FeatureProvider",
    "FieldAggregator",
    "ImportedWeights",
    "ImportsWeights",
    "LossSet",
    "ModelFamily",
    "PerceptionHead",
    "RayAggregator",
    "StressCase",
    "ViewSelector",
]
