"""What every dataset shares, written once: the config fields (``DatasetConfig``), and ``DatasetBase``, which checks the
depth range, the image size and the validation level, resolves the root folder, refuses an unknown split and keeps
each scene once it is read. A dataset subclasses it and says only how its layout lists scenes and reads one
(nerfstudio's DataParser + InputDataset split, in one class).

    class MyScenes(DatasetBase):
        def list_scenes(self, split): ...        # scene names of "train" or "unseen"
        def read_scene(self, name): ...          # a Scene (frames decoded lazily through Scene.load_frame)
"""

from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Optional, Sequence

from gpnerf_core.data.checks import check_validation_level
from gpnerf_core.data.dataset import SPLITS, SceneDataset
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.types import Scene


@dataclass
class DatasetConfig:
    """Where the scenes are, the size frames are loaded at and the ray-sampling range: the fields every dataset's config
    has (it subclasses this one, overriding a default where its own differs; what a field means for one dataset, what
    ``root`` holds or what a size of 0 selects, is in that config's class docstring)."""

    content_keys: ClassVar[tuple[str, ...]] = ()
    """Fields whose value changes what a scene of a given name holds (a generated dataset's seed): a per-scene model
    (``engine.fitted_data``) is refused on a value other than the one it was fitted with."""
    name: str = ""
    """Registry name of the dataset (each subclass defaults it to its own)."""
    root: str = ""
    """Folder holding the dataset's scenes."""
    height: int = 240
    """Image height frames are loaded at, pixels."""
    width: int = 320
    """Image width frames are loaded at, pixels."""
    near: float = 0.1
    """Ray-sampling near bound, metres (training and evaluation alike)."""
    far: float = 6.0
    """Ray-sampling far bound, metres (training and evaluation alike)."""
    scenes: list[str] = field(default_factory=list)
    """Scenes to train on, by folder name under ``root``; empty = the dataset's shipped list (its protocol's)."""
    unseen_scenes: Optional[list[str]] = None
    """Scenes never trained on, evaluated for generalization. null (the default): the dataset's shipped unseen list
    less the scenes ``scenes`` names, and none when ``scenes`` names only scenes of your own (none shipped); [] = no
    unseen scenes; a list = those."""
    validate: str = "quick"
    """Check the chosen scenes' files before training: quick (every file indexed, image sizes, poses finite and rigid),
    full (also decode every frame and check its labels) or off."""


MAX_FAR = 1e6
"""The largest ``far`` in metres (1000 km): past it no scene is reconstructed, and a far like 1e30 puts float32 sample
points where their squares overflow (a nan loss in training instead of a refusal)."""


def check_depth_range(near: float, far: float, *, automatic: bool = False) -> tuple[float, float]:
    """``(near, far)`` in metres when ``0 < near < far <= MAX_FAR``; with ``automatic`` both 0 (taken from the data)
    also passes.

    Raises:
        ConfigError: naming the key at fault (``dataset.near``, ``dataset.far``, or both when near >= far) and what is
            expected.
    """
    if automatic and near == 0 and far == 0:
        return 0.0, 0.0
    both = "both 0 (from the data) or " if automatic else ""
    if automatic and (near == 0) != (far == 0):
        raise ConfigError(f"dataset.near={near}, dataset.far={far}: expected {both}both set, 0 < near < far (metres)")
    if not math.isfinite(near) or near <= 0:
        raise ConfigError(f"dataset.near={near}: expected {both}a finite distance > 0 (metres)")
    if not math.isfinite(far) or not 0 < far <= MAX_FAR:
        raise ConfigError(f"dataset.far={far}: expected {both}a finite distance in (dataset.near={near}, {MAX_FAR:g}] (metres)")
    if near >= far:
        raise ConfigError(f"dataset.near={near}, dataset.far={far}: expected {both}near < far (metres)")
    return float(near), float(far)


def check_image_size(height: int, width: int, *, zero: str = "", multiple: int = 1) -> tuple[int, int] | None:
    """``(height, width)`` in pixels, or None when both are 0 and ``zero`` says what 0 selects (``"the files' size"``).

    Args:
        multiple: both sides must be multiples of it (an extractor's coarsest stride).

    Raises:
        ConfigError: naming ``dataset.height`` and ``dataset.width`` and what is expected.
    """
    if zero and height == 0 and width == 0:
        return None
    bad = height < 1 or width < 1 or height % multiple or width % multiple
    if bad:
        sizes = "positive sizes in pixels" + (f", multiples of {multiple}" if multiple > 1 else "")
        raise ConfigError(f"dataset.height={height}, dataset.width={width}; expected "
                          f"{f'both 0 ({zero}) or ' if zero else ''}{sizes}")
    return int(height), int(width)


def from_launch_dir(root: str | Path) -> Path:
    """``root`` with ``~`` expanded; a relative path is joined to the launch directory (Hydra's original working
    directory inside a Hydra run, which may have changed into its output folder, else the current one)."""
    path = Path(root).expanduser()
    if path.is_absolute():
        return path
    base = Path.cwd()
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.utils import get_original_cwd

        if HydraConfig.initialized():
            base = Path(get_original_cwd())
    except ImportError:
        pass
    return base / path


class DatasetBase(SceneDataset):
    """A dataset's shared half: settings checked, root resolved, splits checked, scenes read once.

    Args:
        root: ``dataset.root`` as given ("" allowed when ``root_holds`` is empty: the dataset needs none).
        validate: ``dataset.validate``.
        near, far: the depth range (``automatic_bounds``: both 0 = from the data, which ``read_scene`` then finds).
        root_holds: what the root folder holds, for the messages ("the Replica scene folders"); "" = no root needed.

    Subclasses implement ``list_scenes`` and ``read_scene`` (and ``class_names``, ``ignore_index``).
    """

    def __init__(
        self,
        *,
        root: str | Path,
        validate: str,
        near: float,
        far: float,
        root_holds: str = "",
        automatic_bounds: bool = False,
    ) -> None:
        self.validation = check_validation_level(validate)
        self.near, self.far = check_depth_range(near, far, automatic=automatic_bounds)
        self.root_holds = root_holds
        self._root_given = str(root)
        self._root: Path | None = None
        self._scenes: dict[str, Scene] = {}

    @property
    def root(self) -> Path:
        """The root folder, resolved on first use (relative to the launch directory).

        Raises:
            ConfigError: ``dataset.root`` is empty; DataError: it names no folder.
        """
        if self._root is None:
            if not self._root_given:
                raise ConfigError(f"dataset.root is empty; expected the folder holding {self.root_holds}")
            path = from_launch_dir(self._root_given)
            if not path.is_dir():
                raise DataError(f"{path}: dataset.root folder missing; expected the folder holding {self.root_holds}")
            self._root = path
        return self._root

    def scenes(self, split: str) -> tuple[str, ...]:
        if split not in SPLITS:
            raise ConfigError(f"unknown split {split!r}; expected one of: {', '.join(SPLITS)}")
        return tuple(self.list_scenes(split))

    def load_scene(self, name: str) -> Scene:
        """The scene ``name``, read once (``read_scene``) and kept."""
        if name not in self._scenes:
            self._scenes[name] = self.read_scene(name)
        return self._scenes[name]

    def forget_scenes(self) -> None:
        """Drop the scenes read so far (their files changed: a regenerated cache)."""
        self._scenes = {}

    @abstractmethod
    def list_scenes(self, split: str) -> Sequence[str]:
        """Scene names of ``split`` (``train`` or ``unseen``, already checked)."""

    @abstractmethod
    def read_scene(self, name: str) -> Scene:
        """Read scene ``name``'s cameras and frame lists (a ConfigError for a name outside the splits); frames decode
        lazily through ``Scene.load_frame``."""
