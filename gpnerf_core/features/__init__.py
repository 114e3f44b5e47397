"""Feature providers' 2D features and the feature fields distilled from them (docs/features.md).

A feature provider's per-frame features (``+feature_provider=<name>``): the provider a config selects
(``build_feature_provider``) and its features read through the on-disk cache (``frame_features``, ``FeatureCache``:
memory-mapped shards under ``$GPNERF_CACHE/features/<key>/``). Unrelated to ``gpnerf_core.model.feature_cache``, which
keeps encoded source views of a render. The feature fields a family distils from them: ``field`` (what a family is
handed, the distillation term) and ``compression`` (the per-scene autoencoder). Queries against any feature map or
per-Gaussian / per-point feature matrix (by example, by text, by class prototype): ``queries``."""

from gpnerf_core.features.build import build_feature_provider
from gpnerf_core.features.cache import FeatureCache, cache_root, frame_features, scene_identity

__all__ = ["FeatureCache", "build_feature_provider", "cache_root", "frame_features", "scene_identity"]
