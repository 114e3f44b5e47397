"""Interface of scene datasets."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

from gpnerf_core.data.checks import check_scene_files
from gpnerf_core.errors import ConfigError
from gpnerf_core.types import Scene

SPLITS = ("train", "unseen")


class SceneDataset(ABC):
    """A set of posed, labelled scenes with a fixed class map.

    ``train`` scenes are trained on (their ``Scene.train_frames``) and evaluated on their held-out
    ``Scene.eval_frames``; ``unseen`` scenes never reach training and test generalization.
    """

    validation: str = "quick"
    """How thoroughly ``check_files`` looks before training: ``quick``, ``full`` or ``off`` (the built-in datasets
    set it from ``dataset.validate``)."""

    @property
    @abstractmethod
    def class_names(self) -> tuple[str, ...]:
        """Names of the classes 0..K-1; empty for a dataset whose scenes have no labels (a user's capture), where a
        trained model's own class list is used (``eval``, ``render``, ``finetune`` from its checkpoint)."""

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    @abstractmethod
    def ignore_index(self) -> int:
        """Label value of unlabelled pixels."""

    @abstractmethod
    def scenes(self, split: str) -> tuple[str, ...]:
        """Scene names of ``split`` (one of ``SPLITS``)."""

    @abstractmethod
    def load_scene(self, name: str) -> Scene:
        """Load a scene's cameras and frame lists; frames load lazily through ``Scene.load_frame``."""


    def check_files(self, scenes: Sequence[str], level: str) -> list[str]:
        """Problems in the files of ``scenes``, one line each naming the file (or the scene and frame).

        Called before training with ``level = self.validation``. The default loads every scene and checks its poses
        (``quick``), and with ``full`` decodes every frame and checks its values (``gpnerf_core.data.checks``);
        a dataset may check more (checksums) or faster.
        """
        return check_scene_files(self, scenes, level)


def shown_scenes(dataset: SceneDataset, fitted: FittedScenes | None = None) -> list[str]:
    """The scenes a command that shows one may choose from: the unseen ones first, then the training ones; for a
    per-scene model (``fitted``) only the scenes it was fitted on."""
    if fitted is not None:
        return list(fitted.scenes)
    return list(dataset.scenes("unseen")) + list(dataset.scenes("train"))


def chosen_scene(dataset: SceneDataset, key: str, value: str, fitted: FittedScenes | None = None) -> str:
    """The scene a command shows: ``value``, or "" for the first unseen scene, else the first training scene (a
    per-scene model's: its own scene).

    Raises:
        ConfigError: ``value`` names no scene of the dataset (the message lists them, naming ``key``), or a scene a
            per-scene model was not fitted on.
    """
    if fitted is not None and value and value not in fitted.scenes:
        raise ConfigError(f"{key}={value!r}: {fitted.why}; expected {key}={fitted.scenes[0]} or {key} left out")
    scenes = shown_scenes(dataset, fitted)
    name = value or (scenes[0] if scenes else "")
    if name not in scenes:
        raise ConfigError(f"{key}={name!r} is not a scene of this dataset; known: {', '.join(scenes)}")
    return name


@dataclass(frozen=True)
class FittedScenes:
    """The scenes a per-scene model was fitted on (from its checkpoint): the only ones it can render.

    Attributes:
        scenes: their names; why: one phrase for refusals (``model 'semantic_nerf' was fitted on scene 'layout_00'
            alone (checkpoint ...): a per-scene model renders only its scene``).
    """

    scenes: tuple[str, ...]
    why: str
