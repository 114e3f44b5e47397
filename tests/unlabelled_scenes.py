"""A test-only dataset of scenes without labels: the embedded rooms with some scenes' labels dropped, and optionally no
class list at all (as a user's capture without labels, whose model classes come from a checkpoint).

Registered as ``dataset=unlabelled_embedded`` by ``gpnerf_register_datasets`` below: in-process through
``registry_with_unlabelled()``, and in a subprocess as an installed plugin (``install(root)`` writes a distribution
whose entry point is this module; put ``root`` and this folder on ``PYTHONPATH``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import torch

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_core.errors import ConfigError
from gpnerf_core.types import Frame, Scene
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes, EmbeddedScenesConfig

DISTRIBUTION = "gpnerf-test-unlabelled"


@dataclass
class UnlabelledScenesConfig(EmbeddedScenesConfig):
    """The embedded rooms; ``without_labels`` scenes lose their labels, ``class_list=false`` drops the class list."""

    name: str = "unlabelled_embedded"
    """Registry name of this dataset."""
    without_labels: list[str] = field(default_factory=list)
    """Scenes whose labels are dropped (``Scene.labelled`` False, every label the ignore index); empty = all."""
    class_list: bool = True
    """False: ``class_names`` is empty, as a capture without a class list."""


class UnlabelledScenes(EmbeddedScenes):
    """``EmbeddedScenes`` whose chosen scenes have no labels (and no instance ids)."""

    def __init__(self, without_labels: Sequence[str] = (), class_list: bool = True, **options) -> None:
        super().__init__(**options)
        known = self.params.scene_names("train") + self.params.scene_names("unseen")
        unknown = [name for name in without_labels if name not in known]
        if unknown:
            raise ConfigError(f"dataset.without_labels has {unknown[0]!r}; expected some of {', '.join(known)}")
        self.without_labels = set(without_labels or known)
        self.class_list = bool(class_list)

    @property
    def class_names(self) -> tuple[str, ...]:
        return super().class_names if self.class_list else ()

    def load_scene(self, name: str) -> Scene:
        scene = super().load_scene(name)
        if name not in self.without_labels:
            return scene
        ignore = self.ignore_index

        def load_frame(index: int) -> Frame:
            frame = scene.load_frame(index)
            return dataclasses.replace(frame, semantic=torch.full_like(frame.semantic, ignore), instance=None)

        return dataclasses.replace(scene, load_frame=load_frame, labelled=False)


@hookimpl
def gpnerf_register_datasets() -> list[ComponentSpec]:
    return [ComponentSpec("unlabelled_embedded", UnlabelledScenes, UnlabelledScenesConfig,
                          "embedded rooms without labels (tests)")]


def install(root: Path) -> Path:
    """Write a distribution into ``root`` whose ``gpnerf`` entry point is this module; returns ``root``."""
    info = root / "gpnerf_test_unlabelled-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DISTRIBUTION}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[gpnerf]\ngpnerf_test_unlabelled = unlabelled_scenes\n")
    return root
