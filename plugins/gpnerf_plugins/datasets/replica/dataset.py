"""The ``replica`` (Semantic-NeRF renders) and ``replica_instance`` (DM-NeRF renders) datasets and their checkers.

Differences from the reference loaders (GP-NeRF ``gpnerf/data_loaders/replica_dataset.py`` and
``replica_instance_dataset.py``; REFERENCE.md 5.1, 5.2, 7):

* Intrinsics (C5): the reference hard-codes fx=320, cx=320, fy=319.5, cy=229.5 for 640x480 (cx and fy swapped, cy
  10 px off, and never rescaled in ``replica``). Here fx = fy = W / (2 tan(hfov / 2)), cx = (W - 1) / 2,
  cy = (H - 1) / 2 at the loaded size, i.e. 320, 320, 319.5, 239.5 at 640x480 and 160, 160, 159.5, 119.5 at 320x240.
* Scenes (C6): the released training list holds all eight scenes, the two test scenes included. ``heldout`` (default)
  trains on six and tests on office_0 and room_0; ``paper_parity`` reproduces the released lists for comparison with
  published numbers.
* Frames (C7): ``replica_instance`` evaluates on positions 600, 620, ..., 880 while the reference trains on every even
  position, all of those included. ``heldout`` removes them from training; ``paper_parity`` keeps the overlap.
* Poses (C17): a NaN/Inf pose or a pose count that does not match the frames is a DataError naming the file, never a
  silently shifted frame list.
* Labels: raw ids above 101 are a DataError (``strict_labels``) instead of being clipped into the ignore class.
"""

from __future__ import annotations

import dataclasses
import functools
import re
import warnings
from abc import abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from gpnerf_core import ConfigError, DataError, DatasetBase, DatasetConfig, Frame, Scene, check_image_size
from gpnerf_plugins.datasets.common.scene_lists import chosen_scenes, chosen_unseen, missing_scene
from gpnerf_plugins.datasets.replica.check import check_replica_instance_layout, check_replica_layout
from gpnerf_plugins.datasets.replica.classes import CLASS_NAMES, IGNORE_INDEX, map_raw_labels
from gpnerf_plugins.datasets.replica.dm_layout import InstanceSequence
from gpnerf_plugins.datasets.replica.layout import ReplicaSequence
from gpnerf_plugins.datasets.replica.splits import (
    INSTANCE_SCENES_FILE,
    check_frame_rule,
    protocol_files,
    read_split_file,
    stepped_positions,
)

__all__ = [
    "ReplicaInstanceScenes",
    "ReplicaInstanceScenesConfig",
    "ReplicaScenes",
    "ReplicaScenesConfig",
    "check_replica_instance_layout",
    "check_replica_layout",
]

SEQUENCE = re.compile(r"Sequence_(\d+)")
UNSEEN_SEQUENCE = "Sequence_1"
"""The unseen split's sequence of each unseen scene (the reference's); a scene without one uses its lowest-numbered."""


@dataclass
class ReplicaScenesConfig(DatasetConfig):
    """Options of Semantic-NeRF's Replica renders.

    ``root`` holds <scene>/Sequence_<n>/; a relative path is taken from the launch directory. ``height`` and ``width``
    both 0 load the files' size.
    """

    name: str = "replica"
    """Registry name of this dataset."""
    protocol: str = "heldout"
    """heldout: 6 training scenes, office_0 and room_0 unseen; paper_parity: the released lists (leaky)."""
    far: float = 10.0
    """Ray-sampling far bound, metres."""
    hfov_deg: float = 90.0
    """Horizontal field of view of the renders, degrees (Semantic-NeRF: 90)."""
    eval_start: int = 2
    """Held-out frames are the positions [eval_start:eval_stop:eval_step][:eval_count] of each sequence."""
    eval_stop: int = 700
    """End (exclusive) of the held-out position range."""
    eval_step: int = 20
    """Spacing of held-out positions."""
    eval_count: int = 10
    """At most this many held-out frames per sequence (0 = no cap); all other frames are training frames."""
    strict_labels: bool = True
    """Raw label ids above 101 raise a DataError (false: they become ignore, as the reference's clipping does)."""


@dataclass
class ReplicaInstanceScenesConfig(DatasetConfig):
    """Options of DM-NeRF's Replica renders.

    ``root`` holds <scene>/ in the DM-NeRF Replica layout; a relative path is taken from the launch directory.
    ``height`` and ``width`` both 0 load the files' size.
    """

    name: str = "replica_instance"
    """Registry name of this dataset."""
    protocol: str = "heldout"
    """heldout: evaluation frames removed from training; paper_parity: the reference's overlapping frame sets."""
    hfov_deg: float = 90.0
    """Horizontal field of view of the renders, degrees (Semantic-NeRF: 90)."""
    eval_start: int = 600
    """Evaluation frames are the positions [eval_start:eval_stop:eval_step] (reference: [0:900:20][30:] = 600..880)."""
    eval_stop: int = 900
    """End (exclusive) of the evaluation position range."""
    eval_step: int = 20
    """Spacing of evaluation positions."""
    train_stop: int = 900
    """Training frames are the positions [0:train_stop:train_step] (minus evaluation frames under heldout)."""
    train_step: int = 2
    """Spacing of training positions."""
    strict_labels: bool = True
    """Raw class ids above 101 in an optional semantic_class folder raise a DataError (false: they become ignore)."""


class _ReplicaDataset(DatasetBase):
    """What both Replica datasets share: load settings, the 51 classes, a lazily resolved root, one reader per scene.

    Subclasses define ``_reader(name)`` (validates the scene name, opens its folder) and ``frame_split``.
    """

    def __init__(
        self,
        root: str,
        protocol: str,
        height: int,
        width: int,
        near: float,
        far: float,
        hfov_deg: float,
        strict_labels: bool,
        validate: str,
    ) -> None:
        super().__init__(root=root, validate=validate, near=near, far=far,
                         root_holds="the Replica scene folders (office_0/, ...)")
        self.size = check_image_size(height, width, zero="the files' size")
        if not 0.0 < hfov_deg < 180.0:
            raise ConfigError(f"dataset.hfov_deg={hfov_deg}; expected a field of view in (0, 180) degrees")
        self.protocol = protocol
        self.hfov_deg = float(hfov_deg)
        self.strict_labels = strict_labels

    @property
    def class_names(self) -> tuple[str, ...]:
        return CLASS_NAMES

    @property
    def ignore_index(self) -> int:
        return IGNORE_INDEX

    @abstractmethod
    def frame_split(self, num_frames: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """``(train_frames, eval_frames)`` positions of a scene of ``num_frames`` frames."""

    @abstractmethod
    def _reader(self, name: str) -> ReplicaSequence:
        """The reader of scene ``name``; ConfigError for a name outside the splits."""

    def _scene_folder(self, scene: str, expected: str) -> Path:
        folder = self.root / scene
        if not folder.is_dir():
            raise missing_scene(self.root, scene, expected)
        return folder

    def read_scene(self, name: str) -> Scene:
        reader = self._reader(name)
        split = self.frame_split(reader.num_frames)
        overlap = self.protocol == "paper_parity"
        loaded = reader.scene(name=name, split=split, near=self.near, far=self.far, allow_overlap=overlap)
        return dataclasses.replace(loaded, load_frame=functools.partial(self._load_frame, reader))

    def _load_frame(self, reader: ReplicaSequence, index: int) -> Frame:
        # The reader returns raw Replica ids (no label_map) so that ids outside Replica's table can be reported.
        frame = reader.load_frame(index)
        path = reader.files[index].semantic
        if path is None:  # no semantic_class folder: already all IGNORE_INDEX
            return frame
        return dataclasses.replace(frame, semantic=map_raw_labels(frame.semantic, path, strict=self.strict_labels))


class ReplicaScenes(_ReplicaDataset):
    """Semantic-NeRF's Replica renders ``<root>/<scene>/Sequence_<n>/``: 51 classes, scenes ``office_0/Sequence_1``, ...

    ``train`` = every ``Sequence_<n>`` folder of every training scene (Semantic-NeRF ships ``Sequence_1`` and
    ``Sequence_2``); ``unseen`` = ``Sequence_1`` of every unseen scene (its lowest-numbered sequence if it has no
    ``Sequence_1``). The scenes are the protocol's shipped lists unless ``scenes`` / ``unseen_scenes`` name folders
    under ``root``. Each sequence holds out the positions ``[eval_start:eval_stop:eval_step][:eval_count]`` (2, 22,
    ..., 182 by default) as ``eval_frames`` and trains on all others. Construction reads only the split files;
    ``scenes`` lists the sequence folders, scenes are indexed on first ``load_scene`` and frames decoded on each
    ``Scene.load_frame`` call.
    """

    def __init__(
        self,
        root: str = ReplicaScenesConfig.root,
        protocol: str = ReplicaScenesConfig.protocol,
        height: int = ReplicaScenesConfig.height,
        width: int = ReplicaScenesConfig.width,
        near: float = ReplicaScenesConfig.near,
        far: float = ReplicaScenesConfig.far,
        validate: str = ReplicaScenesConfig.validate,
        hfov_deg: float = ReplicaScenesConfig.hfov_deg,
        eval_start: int = ReplicaScenesConfig.eval_start,
        eval_stop: int = ReplicaScenesConfig.eval_stop,
        eval_step: int = ReplicaScenesConfig.eval_step,
        eval_count: int = ReplicaScenesConfig.eval_count,
        strict_labels: bool = ReplicaScenesConfig.strict_labels,
        scenes: Sequence[str] = (),
        unseen_scenes: Sequence[str] | None = None,
    ) -> None:
        train_file, test_file = protocol_files(protocol)
        super().__init__(root, protocol, height, width, near, far, hfov_deg, strict_labels, validate)
        check_frame_rule("eval_start/eval_stop/eval_step/eval_count", eval_start, eval_stop, eval_step, eval_count)
        self.eval_rule = (eval_start, eval_stop, eval_step, eval_count)
        shipped_train = read_split_file(train_file)
        self.train_scene_names = chosen_scenes("scenes", scenes, shipped_train)
        self.test_scene_names = chosen_unseen(unseen_scenes, read_split_file(test_file), train=self.train_scene_names,
                                              train_given=bool(scenes), shipped_train=shipped_train)
        self._sequences: dict[str, tuple[str, ...]] = {}
        leaked = sorted(set(self.train_scene_names) & set(self.test_scene_names))
        if leaked:
            warnings.warn(
                f"replica protocol {protocol!r} trains on the unseen scenes {', '.join(leaked)} (the released split's "
                "leak); use it only to compare with published numbers",
                UserWarning,
                stacklevel=2,
            )

    def list_scenes(self, split: str) -> tuple[str, ...]:
        """``<scene>/Sequence_<n>`` names of ``split`` (reads the scene folders' listings)."""
        if split == "train":
            return tuple(f"{scene}/{sequence}" for scene in self.train_scene_names for sequence in self.sequences(scene))
        return tuple(name for scene in self.test_scene_names for name in self._unseen_names(scene))

    def sequences(self, scene: str) -> tuple[str, ...]:
        """The ``Sequence_<n>`` folders of ``scene``, by number; DataError when the scene has none."""
        if scene not in self._sequences:
            folder = self._scene_folder(scene, f"Semantic-NeRF's Replica render of {scene} (Sequence_<n>/ folders)")
            found = sorted(
                (int(match.group(1)), entry.name)
                for entry in folder.iterdir()
                if entry.is_dir() and (match := SEQUENCE.fullmatch(entry.name))
            )
            if not found:
                raise DataError(f"{folder}: no Sequence_<n>/ folders; expected Semantic-NeRF's Replica render layout")
            self._sequences[scene] = tuple(name for _, name in found)
        return self._sequences[scene]

    def _unseen_names(self, scene: str) -> tuple[str]:
        sequences = self.sequences(scene)
        return (f"{scene}/{UNSEEN_SEQUENCE if UNSEEN_SEQUENCE in sequences else sequences[0]}",)

    def frame_split(self, num_frames: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """``(train_frames, eval_frames)`` positions of a sequence of ``num_frames`` frames; disjoint."""
        held = stepped_positions(num_frames, *self.eval_rule)
        held_set = set(held)
        return tuple(i for i in range(num_frames) if i not in held_set), held

    def _reader(self, name: str) -> ReplicaSequence:
        scene, _, sequence = name.partition("/")
        if scene in self.train_scene_names:
            allowed = self.sequences(scene)
        elif scene in self.test_scene_names:
            allowed = tuple(known.split("/")[1] for known in self._unseen_names(scene))
        else:
            choices = ", ".join(dict.fromkeys(self.train_scene_names + self.test_scene_names))
            raise ConfigError(
                f"unknown scene {name!r} for protocol {self.protocol!r}; expected <scene>/Sequence_<n> with a scene "
                f"of: {choices}"
            )
        if sequence not in allowed:
            raise ConfigError(f"unknown scene {name!r}; expected one of: {', '.join(f'{scene}/{a}' for a in allowed)}")
        folder = self._scene_folder(scene, f"Semantic-NeRF's Replica render of {scene}")
        return ReplicaSequence(folder / sequence, hfov_deg=self.hfov_deg, size=self.size, ignore_index=IGNORE_INDEX)


class ReplicaInstanceScenes(_ReplicaDataset):
    """DM-NeRF's Replica renders ``<root>/<scene>/``: raw instance ids per frame, scenes named ``office_0``.

    The per-scene setting of GP-NeRF's instance experiments: the ``train`` split is the scene list
    ``replica_instance.txt`` (or ``scenes``) and ``unseen`` is empty (or ``unseen_scenes``). Evaluation frames are the positions
    ``[eval_start:eval_stop:eval_step]`` (600, 620, ..., 880), training frames ``[0:train_stop:train_step]`` (the even
    positions) minus the evaluation frames; ``paper_parity`` keeps them in training, as the reference does.
    ``Frame.semantic`` is all ignore unless the scene has a ``semantic_class`` folder, mapped to the 51 classes.
    """

    def __init__(
        self,
        root: str = ReplicaInstanceScenesConfig.root,
        protocol: str = ReplicaInstanceScenesConfig.protocol,
        height: int = ReplicaInstanceScenesConfig.height,
        width: int = ReplicaInstanceScenesConfig.width,
        near: float = ReplicaInstanceScenesConfig.near,
        far: float = ReplicaInstanceScenesConfig.far,
        validate: str = ReplicaInstanceScenesConfig.validate,
        hfov_deg: float = ReplicaInstanceScenesConfig.hfov_deg,
        eval_start: int = ReplicaInstanceScenesConfig.eval_start,
        eval_stop: int = ReplicaInstanceScenesConfig.eval_stop,
        eval_step: int = ReplicaInstanceScenesConfig.eval_step,
        train_stop: int = ReplicaInstanceScenesConfig.train_stop,
        train_step: int = ReplicaInstanceScenesConfig.train_step,
        strict_labels: bool = ReplicaInstanceScenesConfig.strict_labels,
        scenes: Sequence[str] = (),
        unseen_scenes: Sequence[str] | None = None,
    ) -> None:
        protocol_files(protocol)  # same protocol names as ``replica``
        super().__init__(root, protocol, height, width, near, far, hfov_deg, strict_labels, validate)
        check_frame_rule("eval_start/eval_stop/eval_step", eval_start, eval_stop, eval_step)
        check_frame_rule("train_stop/train_step", 0, train_stop, train_step)
        self.eval_rule = (eval_start, eval_stop, eval_step)
        self.train_rule = (0, train_stop, train_step)
        self.scene_names = chosen_scenes("scenes", scenes, read_split_file(INSTANCE_SCENES_FILE))
        self.unseen_scene_names = chosen_unseen(unseen_scenes, (), train=self.scene_names, train_given=bool(scenes))
        if protocol == "paper_parity":
            warnings.warn(
                "replica_instance protocol 'paper_parity' trains on its evaluation frames (the reference's overlap); "
                "use it only to compare with published numbers",
                UserWarning,
                stacklevel=2,
            )

    def list_scenes(self, split: str) -> tuple[str, ...]:
        return self.scene_names if split == "train" else self.unseen_scene_names

    def frame_split(self, num_frames: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """``(train_frames, eval_frames)`` positions; they overlap only under ``paper_parity``."""
        held = stepped_positions(num_frames, *self.eval_rule)
        pool = stepped_positions(num_frames, *self.train_rule)
        if self.protocol == "paper_parity":
            return pool, held
        held_set = set(held)
        return tuple(i for i in pool if i not in held_set), held

    def _reader(self, name: str) -> ReplicaSequence:
        known = self.scene_names + self.unseen_scene_names
        if name not in known:
            raise ConfigError(f"unknown scene {name!r}; expected one of: {', '.join(known)}")
        folder = self._scene_folder(name, "DM-NeRF's Replica render (rgb/, depth/, semantic_instance/, traj_w_c.txt)")
        return InstanceSequence(folder, hfov_deg=self.hfov_deg, size=self.size, ignore_index=IGNORE_INDEX)
