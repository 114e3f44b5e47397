"""The ``embedded`` dataset: generated pybullet rooms, read through the Replica-layout reader."""

from __future__ import annotations

import functools
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from gpnerf_core import (
    ConfigError,
    DataError,
    DatasetBase,
    DatasetConfig,
    Scene,
    check_scene_files,
    from_launch_dir,
)
from gpnerf_plugins.datasets.common.scene_lists import chosen_scenes, chosen_unseen
from gpnerf_plugins.datasets.embedded import CLASS_NAMES, IGNORE_INDEX, SEQUENCE, SceneSetParams, ensure_generated
from gpnerf_plugins.datasets.embedded.generation import check_params, damaged_files
from gpnerf_plugins.datasets.replica.layout import ReplicaSequence, every_nth_split


@dataclass
class EmbeddedScenesConfig(DatasetConfig):
    """Options of the generated rooms.

    ``root`` is the folder of a generated set (generated there if empty or missing); "" = the cache ($GPNERF_CACHE or
    ~/.cache/gpnerf). A relative path is taken from the launch directory.
    """

    content_keys = ("seed", "textureless")  # another seed generates other rooms under the same names
    name: str = "embedded"
    """Registry name of this dataset."""
    num_train_scenes: int = 4
    """Layouts whose train frames are trained on (eval frames held out)."""
    num_unseen_scenes: int = 1
    """Layouts never trained on, for the generalization test."""
    frames_per_scene: int = 36
    """Frames along each layout's camera orbit."""
    height: int = 96
    """Rendered image height, pixels (a multiple of 4 for `resunet_fpn`, whose maps have 1/4 and 1/2 of its cells)."""
    width: int = 128
    """Rendered image width, pixels."""
    seed: int = 0
    """Seed of layouts and trajectories; the same seed gives byte-identical files."""
    eval_every: int = 6
    """Every eval_every-th frame (starting at eval_every // 2) is a held-out eval frame; 0 = none."""
    near: float = 0.2
    """Ray-sampling near bound, metres (the closest surface seen is about 0.5 m away)."""
    far: float = 6.5
    """Ray-sampling far bound, metres (the farthest wall point seen is under 6 m away)."""
    textureless: bool = False
    """Render every surface in one flat colour (same layouts and cameras; the stress suite's textureless case)."""


class EmbeddedScenes(DatasetBase):
    """Rooms of pybullet_data objects, generated on first ``load_scene`` into ``root`` or the cache.

    Scenes ``layout_00, ...`` form the train split and ``unseen_00, ...`` the unseen split. Constructing the
    dataset validates its parameters but renders nothing. Frames are decoded on each ``Scene.load_frame`` call
    (no caching; a 120x160 frame decodes in about a millisecond).
    """

    def __init__(
        self,
        root: str = EmbeddedScenesConfig.root,
        num_train_scenes: int = EmbeddedScenesConfig.num_train_scenes,
        num_unseen_scenes: int = EmbeddedScenesConfig.num_unseen_scenes,
        frames_per_scene: int = EmbeddedScenesConfig.frames_per_scene,
        height: int = EmbeddedScenesConfig.height,
        width: int = EmbeddedScenesConfig.width,
        seed: int = EmbeddedScenesConfig.seed,
        eval_every: int = EmbeddedScenesConfig.eval_every,
        near: float = EmbeddedScenesConfig.near,
        far: float = EmbeddedScenesConfig.far,
        textureless: bool = EmbeddedScenesConfig.textureless,
        validate: str = EmbeddedScenesConfig.validate,
        scenes: Sequence[str] = (),
        unseen_scenes: Sequence[str] | None = None,
    ) -> None:
        super().__init__(root="", validate=validate, near=near, far=far)
        self.params = SceneSetParams(
            num_train_scenes, num_unseen_scenes, frames_per_scene, height, width, seed, bool(textureless)
        )
        generated = self.params.scene_names("train") + self.params.scene_names("unseen")
        self._lists = {
            "train": chosen_scenes("scenes", scenes, self.params.scene_names("train")),
            "unseen": chosen_scenes("unseen_scenes", unseen_scenes, ()),
        }
        for key, names in (("scenes", self._lists["train"]), ("unseen_scenes", self._lists["unseen"])):
            unknown = [name for name in names if name not in generated]
            if unknown:
                raise ConfigError(
                    f"dataset.{key} has {unknown[0]!r}; the embedded set generates {', '.join(generated)} "
                    "(dataset.num_train_scenes / dataset.num_unseen_scenes)"
                )
        self._lists["unseen"] = chosen_unseen(
            unseen_scenes, self.params.scene_names("unseen"), train=self._lists["train"], train_given=bool(scenes),
            shipped_train=self.params.scene_names("train"),
        )
        every_nth_split(frames_per_scene, eval_every)  # raises ConfigError for a bad eval_every
        self.eval_every = eval_every
        self._set_given = from_launch_dir(root) if root else None  # None: the cache
        self._set_folder: Path | None = None
        self._hfov = 0.0

    @property
    def class_names(self) -> tuple[str, ...]:
        return CLASS_NAMES

    @property
    def ignore_index(self) -> int:
        return IGNORE_INDEX

    def list_scenes(self, split: str) -> tuple[str, ...]:
        return self._lists[split]

    def prepare(self) -> Path:
        """Generate the set if needed (once) and return its folder."""
        if self._set_folder is None:
            root = ensure_generated(self.params, self._set_given)
            info = check_params(root, self.params)
            if tuple(info.get("class_names", ())) != CLASS_NAMES or info.get("ignore_index") != IGNORE_INDEX:
                raise DataError(
                    f"{root / 'classes.json'}: class map {info.get('class_names')} (ignore {info.get('ignore_index')}); "
                    f"expected {list(CLASS_NAMES)} (ignore {IGNORE_INDEX})"
                )
            self._hfov = float(info["hfov_deg"])
            self._set_folder = root
        return self._set_folder

    def check_files(self, scenes: Sequence[str], level: str) -> list[str]:
        """The generic check, after comparing the files with the generator's checksum list (sizes and contents, at
        ``quick`` as at ``full``).

        A damaged set in the cache is regenerated (with a note on stderr); a damaged set in ``dataset.root`` is reported
        with how to regenerate it.
        """
        if level == "off":
            return []
        root = self.prepare()
        damaged = damaged_files(root, list(scenes))
        if damaged and self._set_given is None:
            print(f"note: the cached embedded scenes in {root} are damaged ({damaged[0]}); regenerating", file=sys.stderr)
            shutil.rmtree(root)
            self._set_folder = None
            self.forget_scenes()
            root = self.prepare()
            damaged = damaged_files(root, list(scenes))
        if damaged:
            fix = f"regenerate: delete {root} and run again (it is rendered into an empty folder)"
            return [f"{problem}; {fix}" for problem in damaged]
        return check_scene_files(self, scenes, level)

    def read_scene(self, name: str) -> Scene:
        known = self.params.scene_names("train") + self.params.scene_names("unseen")
        if name not in known:
            raise ConfigError(f"unknown scene {name!r}; expected one of: {', '.join(known)}")
        sequence = ReplicaSequence(
            self.prepare() / name / SEQUENCE,
            hfov_deg=self._hfov,
            label_map=np.arange(len(CLASS_NAMES)),
            ignore_index=IGNORE_INDEX,
        )
        split = functools.partial(every_nth_split, every=self.eval_every)
        return sequence.scene(name=name, split=split, near=self.near, far=self.far)
