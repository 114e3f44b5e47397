"""Class map and the pybullet_data assets each class is built from."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

from gpnerf_core import DataError

CLASS_NAMES: tuple[str, ...] = (
    "floor",
    "wall",
    "table",
    "shelf",
    "duck",
    "teddy",
    "toy_block",
    "tray",
    "misc_object",
)
IGNORE_INDEX = 255
"""Semantic label of pixels that hit nothing."""
BACKGROUND_INSTANCE = 0
"""Instance id of the floor, the walls and pixels that hit nothing; every other body gets 1, 2, ..."""

# random_urdfs/NNN ids each split may draw "misc_object" meshes from, so unseen layouts show unseen shapes.
MISC_IDS = {"train": range(0, 800), "unseen": range(800, 1000)}

FLOOR_FILE = "plane.urdf"
FLOOR_TEXTURE = "checker_blue.png"
WALL_MESH = "cube.obj"
WALL_TEXTURES: tuple[str, ...] = ("colors16.png", "cube.png", "jenga/jenga.png")


@dataclass(frozen=True)
class Asset:
    """A kind of object: a pybullet_data model and how to stand it up.

    Attributes:
        key: asset name used in layouts.
        class_name: its semantic class (one of ``CLASS_NAMES``).
        file: path inside pybullet_data (``{id:03d}`` is filled for random_urdfs).
        upright: Euler angles (rad, xyz) that stand the model on its base with z up.
        size_range: (min, max) largest horizontal extent in metres the model is scaled to.
        rests_on_origin: the model's origin is its floor contact (the table: legs have no collision shape).
    """

    key: str
    class_name: str
    file: str
    upright: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size_range: tuple[float, float] = (0.2, 0.3)
    rests_on_origin: bool = False

    @property
    def class_id(self) -> int:
        return CLASS_NAMES.index(self.class_name)

    @property
    def is_sdf(self) -> bool:
        return self.file.endswith(".sdf")


_HALF_PI = math.pi / 2
ASSETS: dict[str, Asset] = {
    a.key: a
    for a in (
        Asset("table", "table", "table/table.urdf", size_range=(1.0, 1.25), rests_on_origin=True),
        Asset("shelf", "shelf", "kiva_shelf/model.sdf", size_range=(0.6, 0.8)),
        Asset("duck", "duck", "duck_vhacd.urdf", upright=(_HALF_PI, 0.0, 0.0), size_range=(0.3, 0.4)),
        Asset("teddy", "teddy", "teddy_vhacd.urdf", upright=(_HALF_PI, 0.0, 0.0), size_range=(0.28, 0.36)),
        Asset("lego", "toy_block", "lego/lego.urdf", size_range=(0.16, 0.24)),
        Asset("jenga", "toy_block", "jenga/jenga.urdf", size_range=(0.3, 0.4)),
        Asset("tray", "tray", "tray/traybox.urdf", size_range=(0.45, 0.6)),
        Asset("mug", "misc_object", "objects/mug.urdf", size_range=(0.18, 0.26)),
        Asset("random", "misc_object", "random_urdfs/{id:03d}/{id:03d}.urdf", size_range=(0.25, 0.4)),
    )
}
TABLE_TOP_ASSETS = ("duck", "teddy", "lego", "jenga", "mug", "random")
FLOOR_ASSETS = ("duck", "teddy", "tray", "jenga", "random", "mug")


@functools.cache
def data_path() -> Path:
    """The pybullet_data folder (the meshes and textures ship with the pybullet package)."""
    try:
        import pybullet_data
    except ImportError as exc:
        raise DataError(f"pybullet_data is not importable ({exc}); expected the pybullet package to be installed") from None
    return Path(pybullet_data.getDataPath())


def asset_file(asset: Asset, mesh_id: int | None = None) -> Path:
    """Absolute path of ``asset``'s model file (``mesh_id`` selects a random_urdfs model)."""
    rel = asset.file.format(id=mesh_id) if "{id" in asset.file else asset.file
    path = data_path() / rel
    if not path.is_file():
        raise DataError(f"{path}: missing from pybullet_data; expected the model of asset {asset.key!r}")
    return path
