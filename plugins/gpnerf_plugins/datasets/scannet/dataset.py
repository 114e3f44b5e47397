"""The ``scannet`` dataset: ScanNet scenes in the Semantic-Ray export layout, labelled with the 20 benchmark classes.

``<root>/<sceneXXXX_YY>/`` folders (see ``scannet.files``) plus ``<root>/scannetv2-labels.combined.tsv``. The train
and unseen splits are the reference's scene lists, shipped as ``splits/scannet_{train,test,val}.txt``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Optional, Sequence

from gpnerf_core import ConfigError, DataError, DatasetBase, DatasetConfig, Scene, check_image_size, from_launch_dir
from gpnerf_plugins.datasets.scannet.check import check_scannet_layout
from gpnerf_plugins.datasets.scannet.files import SCENE_NAME
from gpnerf_plugins.datasets.scannet.labels import (
    IGNORE_INDEX,
    LABEL_MAP_NAME,
    SCANNET20_CLASS_NAMES,
    LabelMap,
    read_label_map,
)
from gpnerf_plugins.datasets.scannet.scene import DEPTH_ALIGNMENTS, PROTOCOLS, ScanNetScene
from gpnerf_plugins.datasets.common.scene_lists import chosen_scenes, chosen_unseen, present_folders
from gpnerf_plugins.datasets.scannet.splits import read_split

__all__ = ["ScanNetScenes", "ScanNetScenesConfig", "check_scannet_layout", "read_split"]


@dataclass
class ScanNetScenesConfig(DatasetConfig):
    """Options of the ScanNet scenes.

    ``root`` holds the sceneXXXX_YY folders (Semantic-Ray export layout; `data prepare-scannet` writes it). The default
    size is the reference's 240 x 320; ``far`` is one range for training and evaluation (the reference trains with 10).
    """

    name: str = "scannet"
    """Registry name of this dataset."""
    label_map_file: str = ""
    """ScanNet's scannetv2-labels.combined.tsv; "" = <root>/scannetv2-labels.combined.tsv."""
    protocol: str = "heldout"
    """Per-scene frames: "heldout" (numeric order, eval frames never trained on) or "paper_parity" (the reference's
    lexicographic positions, fine-tuning frames overlapping the eval frames)."""
    depth_alignment: str = "intrinsics"
    """intrinsics: register depth to the colour camera with intrinsic/intrinsic_depth.txt; resize: the reference's
    resize as if depth had the colour intrinsics (docs/datasets/scannet.md)."""
    allow_missing_scenes: bool = False
    """Skip split scenes absent from root with a warning instead of failing."""
    scenes: list[str] = field(default_factory=list)
    """Scenes of the train split; empty = the shipped splits/scannet_train.txt (198 scenes)."""
    unseen_scenes: Optional[list[str]] = None
    """Scenes of the unseen split; null = the shipped splits/scannet_test.txt (10 scenes) less those trained on, none
    when dataset.scenes names only scenes outside the shipped splits; [] = none."""


class ScanNetScenes(DatasetBase):
    """ScanNet scenes under ``root``, 20 classes (``ignore_index`` 255).

    Construction validates the options and touches no file. ``scenes`` checks that the split's folders exist;
    ``load_scene`` reads the label map (once), the scene's poses and intrinsics; frames decode per
    ``Scene.load_frame`` (no caching here).
    """

    def __init__(
        self,
        root: str = ScanNetScenesConfig.root,
        label_map_file: str = ScanNetScenesConfig.label_map_file,
        height: int = ScanNetScenesConfig.height,
        width: int = ScanNetScenesConfig.width,
        near: float = ScanNetScenesConfig.near,
        far: float = ScanNetScenesConfig.far,
        validate: str = ScanNetScenesConfig.validate,
        protocol: str = ScanNetScenesConfig.protocol,
        allow_missing_scenes: bool = ScanNetScenesConfig.allow_missing_scenes,
        depth_alignment: str = ScanNetScenesConfig.depth_alignment,
        scenes: Sequence[str] = (),
        unseen_scenes: Sequence[str] | None = None,
    ) -> None:
        if depth_alignment not in DEPTH_ALIGNMENTS:
            raise ConfigError(
                f"dataset.depth_alignment={depth_alignment!r}; expected one of: {', '.join(DEPTH_ALIGNMENTS)}"
            )
        self.depth_alignment = depth_alignment
        if protocol not in PROTOCOLS:
            raise ConfigError(f"dataset.protocol={protocol!r}; expected one of: {', '.join(PROTOCOLS)}")
        super().__init__(root=root, validate=validate, near=near, far=far, root_holds="the sceneXXXX_YY folders")
        self.height, self.width = check_image_size(height, width)
        for key, names in (("scenes", scenes), ("unseen_scenes", unseen_scenes or ())):
            bad = [n for n in names if not SCENE_NAME.match(str(n))]
            if bad:
                raise ConfigError(f"dataset.{key} has {bad[0]!r}; expected scene names sceneXXXX_YY")
        self.label_map_path = from_launch_dir(label_map_file) if label_map_file else None
        self.protocol = protocol
        self.allow_missing_scenes = bool(allow_missing_scenes)
        train = chosen_scenes("scenes", scenes, read_split("train"))
        unseen = chosen_unseen(unseen_scenes, read_split("test"), train=train, train_given=bool(scenes),
                               shipped_train=read_split("train") + read_split("val"))
        self._lists = {"train": train, "unseen": unseen}
        self._label_map: LabelMap | None = None

    @property
    def class_names(self) -> tuple[str, ...]:
        return SCANNET20_CLASS_NAMES

    @property
    def ignore_index(self) -> int:
        return IGNORE_INDEX

    def list_scenes(self, split: str) -> tuple[str, ...]:
        """Scenes of ``split`` present under ``root``, in split-file order.

        Raises:
            DataError: a listed scene folder is missing (naming the first and the count) unless
                ``allow_missing_scenes``, which warns instead; or no listed scene is present at all.
        """
        root = self.root
        listed = self._lists[split]
        present = tuple(name for name in listed if (root / name).is_dir())
        missing = [name for name in listed if name not in present]
        if missing:
            message = (
                f"{root / missing[0]}: missing ({len(missing)} of the {len(listed)} scenes of the {split} split are "
                f"missing; {root} holds: {present_folders(root)}); expected one folder per listed scene"
            )
            if not present:
                raise DataError(f"{message}; none is present")
            if not self.allow_missing_scenes:
                raise DataError(f"{message}; set dataset.allow_missing_scenes=true to skip the missing ones")
            warnings.warn(f"{message}; skipping them (allow_missing_scenes)", stacklevel=2)
        return present

    def label_map(self) -> LabelMap:
        """The raw id -> class map, read once from ``label_map_file`` or ``<root>/scannetv2-labels.combined.tsv``."""
        if self._label_map is None:
            path = self.label_map_path if self.label_map_path is not None else self.root / LABEL_MAP_NAME
            self._label_map = read_label_map(path)
        return self._label_map

    def read_scene(self, name: str) -> Scene:
        if not SCENE_NAME.match(name):
            raise ConfigError(f"unknown scene {name!r}; expected a ScanNet scene name sceneXXXX_YY")
        reader = ScanNetScene(
            self.root / name,
            label_map=self.label_map(),
            height=self.height,
            width=self.width,
            depth_alignment=self.depth_alignment,
        )
        return reader.scene(protocol=self.protocol, near=self.near, far=self.far)
