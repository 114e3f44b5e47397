"""Random room layouts: a table with objects on it, objects on the floor, an optional shelf by a wall."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from gpnerf_plugins.datasets.embedded.catalog import (
    ASSETS,
    FLOOR_ASSETS,
    MISC_IDS,
    TABLE_TOP_ASSETS,
    WALL_TEXTURES,
    Asset,
)

ROOM_HALF_SIZE = 2.8
"""Walls stand at x, y = +-2.8 m around the origin (the camera orbit stays within 1.8 m of it)."""
WALL_HEIGHT = 3.0
WALL_THICKNESS = 0.1
FLOOR_RING = (0.05, 0.5)
"""Floor objects stand this far (m) beyond the table's footprint circle."""
GAP = 0.03
"""Minimum clearance between two footprints, metres."""
MAX_TRIES = 40
"""Placement attempts per object before it is left out."""

# (aabb_min, aabb_max) of an asset at scale 1, upright, yaw 0: supplied by the renderer, which can load models.
ExtentsFn = Callable[[Asset, Optional[int]], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Placement:
    """One body of a layout.

    Attributes:
        asset: key into ``catalog.ASSETS``.
        mesh_id: random_urdfs model number, or None.
        scale: pybullet ``globalScaling``.
        x, y: world position (m) of the centre of the body's footprint.
        yaw: rotation about world z (rad) applied after the asset's upright rotation.
        support: ``"floor"`` or ``"table"``: the surface the body rests on.
        radius: footprint radius (m), used to keep bodies apart.
    """

    asset: str
    mesh_id: int | None
    scale: float
    x: float
    y: float
    yaw: float
    support: str
    radius: float


@dataclass(frozen=True)
class Layout:
    """A room: walls, floor, a table and the objects placed around it.

    The instance id of ``bodies[k]`` is ``k + 1`` (0 is the floor, the walls and empty space).

    Attributes:
        table: the table placement (its centre is the camera orbit's centre).
        table_top: height (m) of the table's top surface.
        objects: every other body (shelf, table-top and floor objects).
        wall_texture: pybullet_data texture file of the walls; wall_tint: RGB multiplier in [0, 1].
        light_direction: direction towards the light (world, unnormalised).
    """

    table: Placement
    table_top: float
    objects: tuple[Placement, ...]
    wall_texture: str
    wall_tint: tuple[float, float, float]
    light_direction: tuple[float, float, float]

    @property
    def bodies(self) -> tuple[Placement, ...]:
        return (self.table, *self.objects)


def _scaled(
    asset: Asset, extents: ExtentsFn, rng: np.random.Generator, mesh_id: int | None
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Draw a size; return (scale, footprint radius, scaled aabb_min, scaled aabb_max)."""
    lo, hi = extents(asset, mesh_id)
    size = rng.uniform(*asset.size_range)
    scale = size / max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-6)
    radius = 0.5 * math.hypot(float(hi[0] - lo[0]), float(hi[1] - lo[1])) * scale
    return scale, radius, lo * scale, hi * scale


def _mesh_id(asset: Asset, split: str, rng: np.random.Generator) -> int | None:
    if "{id" not in asset.file:
        return None
    ids = MISC_IDS[split]
    return int(ids.start + rng.integers(len(ids)))


def _clear(x: float, y: float, radius: float, placed: list[Placement], support: str) -> bool:
    return all(
        math.hypot(x - p.x, y - p.y) >= radius + p.radius + GAP for p in placed if p.support == support
    )


def sample_layout(rng: np.random.Generator, split: str, extents: ExtentsFn) -> Layout:
    """Draw one layout.

    Args:
        rng: the layout's own generator (determinism: the same stream gives the same layout).
        split: ``"train"`` or ``"unseen"``; selects the random_urdfs models misc objects come from.
        extents: unit-scale bounding boxes of the assets.
    """
    table_asset = ASSETS["table"]
    scale, radius, lo, hi = _scaled(table_asset, extents, rng, None)
    offset_r, offset_a = 0.25 * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
    table = Placement(
        "table", None, scale, offset_r * math.cos(offset_a), offset_r * math.sin(offset_a),
        float(rng.uniform(0, math.pi)), "floor", radius,
    )
    table_top = float(hi[2])
    half_x, half_y = float(hi[0] - lo[0]) / 2, float(hi[1] - lo[1]) / 2
    placed: list[Placement] = [table]

    if rng.uniform() < 0.8:
        shelf = ASSETS["shelf"]
        s_scale, s_radius, s_lo, s_hi = _scaled(shelf, extents, rng, None)
        side = int(rng.integers(4))
        normal_angle = side * math.pi / 2
        half_depth = max(float(s_hi[0] - s_lo[0]), float(s_hi[1] - s_lo[1])) / 2
        inward = ROOM_HALF_SIZE - WALL_THICKNESS / 2 - half_depth - 0.02
        along = rng.uniform(-(ROOM_HALF_SIZE - 1.0), ROOM_HALF_SIZE - 1.0)
        cos_a, sin_a = math.cos(normal_angle), math.sin(normal_angle)
        placed.append(Placement(
            "shelf", None, s_scale, inward * cos_a - along * sin_a, inward * sin_a + along * cos_a,
            normal_angle, "floor", s_radius,
        ))

    top: list[Placement] = []
    for _ in range(int(rng.integers(2, 5))):
        asset = ASSETS[TABLE_TOP_ASSETS[int(rng.integers(len(TABLE_TOP_ASSETS)))]]
        mesh_id = _mesh_id(asset, split, rng)
        o_scale, o_radius, _, _ = _scaled(asset, extents, rng, mesh_id)
        yaw = float(rng.uniform(0, 2 * math.pi))
        margin_x, margin_y = half_x - o_radius - 0.02, half_y - o_radius - 0.02
        if margin_x <= 0 or margin_y <= 0:
            continue
        cos_t, sin_t = math.cos(table.yaw), math.sin(table.yaw)
        for _ in range(MAX_TRIES):
            u, v = rng.uniform(-margin_x, margin_x), rng.uniform(-margin_y, margin_y)
            x, y = table.x + u * cos_t - v * sin_t, table.y + u * sin_t + v * cos_t
            if _clear(x, y, o_radius, top, "table"):
                top.append(Placement(asset.key, mesh_id, o_scale, x, y, yaw, "table", o_radius))
                break

    floor: list[Placement] = []
    for _ in range(int(rng.integers(2, 5))):
        asset = ASSETS[FLOOR_ASSETS[int(rng.integers(len(FLOOR_ASSETS)))]]
        mesh_id = _mesh_id(asset, split, rng)
        o_scale, o_radius, _, _ = _scaled(asset, extents, rng, mesh_id)
        yaw = float(rng.uniform(0, 2 * math.pi))
        for _ in range(MAX_TRIES):
            dist = table.radius + o_radius + rng.uniform(*FLOOR_RING)
            angle = rng.uniform(0, 2 * math.pi)
            x, y = table.x + dist * math.cos(angle), table.y + dist * math.sin(angle)
            if _clear(x, y, o_radius, placed + floor, "floor"):
                floor.append(Placement(asset.key, mesh_id, o_scale, x, y, yaw, "floor", o_radius))
                break

    light = rng.normal(size=3)
    light[2] = abs(light[2]) + 1.5
    return Layout(
        table=table,
        table_top=table_top,
        objects=tuple(placed[1:] + top + floor),
        wall_texture=WALL_TEXTURES[int(rng.integers(len(WALL_TEXTURES)))],
        wall_tint=tuple(float(c) for c in rng.uniform(0.7, 1.0, size=3)),
        light_direction=tuple(float(c) for c in light),
    )
