"""Registers the built-in datasets."""

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.datasets.embedded_dataset import EmbeddedScenes, EmbeddedScenesConfig


@hookimpl
def gpnerf_register_datasets() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "embedded",
            EmbeddedScenes,
            EmbeddedScenesConfig,
            "rooms of pybullet_data objects rendered on the CPU (Replica layout), generated once into a cache",
        )
    ]
