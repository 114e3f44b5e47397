"""Embedded default scenes: rooms built from pybullet_data meshes, written in the Replica layout."""

from gpnerf_plugins.datasets.embedded.catalog import BACKGROUND_INSTANCE, CLASS_NAMES, IGNORE_INDEX
from gpnerf_plugins.datasets.embedded.generation import (
    GENERATOR_VERSION,
    HFOV_DEG,
    SEQUENCE,
    SceneSetParams,
    cache_folder,
    default_cache_dir,
    ensure_generated,
    generate,
)

__all__ = [
    "BACKGROUND_INSTANCE",
    "CLASS_NAMES",
    "GENERATOR_VERSION",
    "HFOV_DEG",
    "IGNORE_INDEX",
    "SEQUENCE",
    "SceneSetParams",
    "cache_folder",
    "default_cache_dir",
    "ensure_generated",
    "generate",
]
