"""Build a layout in a headless pybullet world and render RGB, metric depth and labels with TinyRenderer."""

from __future__ import annotations

import functools
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpnerf_core import DataError
from gpnerf_plugins.datasets.embedded.catalog import (
    ASSETS,
    BACKGROUND_INSTANCE,
    CLASS_NAMES,
    FLOOR_FILE,
    FLOOR_TEXTURE,
    IGNORE_INDEX,
    WALL_MESH,
    Asset,
    asset_file,
    data_path,
)
from gpnerf_plugins.datasets.embedded.layout import ROOM_HALF_SIZE, WALL_HEIGHT, WALL_THICKNESS, Layout, Placement

RENDER_NEAR, RENDER_FAR = 0.05, 20.0
"""Clip planes (m) of the render projection; only the z-buffer's precision depends on them."""
AMBIENT, DIFFUSE, SPECULAR = 0.6, 0.45, 0.05


def _pybullet():
    import pybullet

    return pybullet


def projection_matrix(
    height: int, width: int, hfov_deg: float, near: float = RENDER_NEAR, far: float = RENDER_FAR
) -> np.ndarray:
    """OpenGL projection ``[4, 4]`` whose TinyRenderer image has OpenCV intrinsics with pixel centres at integers.

    The camera is ``fx = fy = W / (2 tan(hfov / 2))``, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``. TinyRenderer
    samples pixel ``i`` at raster coordinate ``i`` rather than ``i + 0.5`` (columns) and, after its vertical flip,
    one row low; the ``1/W`` and ``1/H`` terms shift the frustum by half a pixel to compensate.
    """
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([
        [2.0 * f / width, 0.0, 1.0 / width, 0.0],
        [0.0, 2.0 * f / height, 1.0 / height, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def gl_view_matrix(c2w: np.ndarray) -> np.ndarray:
    """OpenGL world-to-camera ``[4, 4]`` of an OpenCV camera-to-world pose (flip y and z: GL looks down -z, y up)."""
    return np.diag([1.0, -1.0, -1.0, 1.0]) @ np.linalg.inv(c2w)


def zbuffer_to_depth(zbuffer: np.ndarray, near: float = RENDER_NEAR, far: float = RENDER_FAR) -> np.ndarray:
    """Camera-z depth (m) from a [0, 1] OpenGL depth buffer of a perspective projection."""
    z = zbuffer.astype(np.float64)
    return far * near / (far - (far - near) * z)


def _column_major(matrix: np.ndarray) -> list[float]:
    return [float(v) for v in matrix.T.reshape(-1)]


def _orientation(p, asset: Asset, yaw: float) -> tuple[float, ...]:
    upright = p.getQuaternionFromEuler(asset.upright)
    turn = p.getQuaternionFromEuler((0.0, 0.0, yaw))
    return p.multiplyTransforms((0, 0, 0), turn, (0, 0, 0), upright)[1]


def _load(p, client: int, asset: Asset, mesh_id: int | None, scale: float, orientation) -> int:
    path = str(asset_file(asset, mesh_id))
    try:
        if asset.is_sdf:
            body = p.loadSDF(path, globalScaling=scale, physicsClientId=client)[0]
            p.resetBasePositionAndOrientation(body, (0, 0, 0), orientation, physicsClientId=client)
        else:
            body = p.loadURDF(
                path, baseOrientation=orientation, globalScaling=scale, useFixedBase=True, physicsClientId=client
            )
    except p.error as exc:
        raise DataError(f"{path}: pybullet could not load it ({exc}); expected a valid model") from None
    return body


@functools.cache
def unit_extents(asset: Asset, mesh_id: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box ``(min, max)`` (m) of ``asset`` at scale 1, upright, yaw 0, origin at 0."""
    p = _pybullet()
    client = p.connect(p.DIRECT)
    try:
        body = _load(p, client, asset, mesh_id, 1.0, _orientation(p, asset, 0.0))
        lo, hi = p.getAABB(body, physicsClientId=client)
    finally:
        p.disconnect(physicsClientId=client)
    return np.asarray(lo), np.asarray(hi)


@dataclass(frozen=True)
class RenderedView:
    """One rendered frame.

    Attributes:
        rgb: ``[H, W, 3]`` uint8.
        depth: ``[H, W]`` float64 camera-z metres, 0 where nothing is hit.
        semantic: ``[H, W]`` uint8 class ids, ``IGNORE_INDEX`` where nothing is hit.
        instance: ``[H, W]`` uint16 instance ids, ``BACKGROUND_INSTANCE`` for floor, walls and empty space.
    """

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray


class RoomRenderer:
    """A private pybullet DIRECT world holding one layout; use as a context manager."""

    def __init__(self, layout: Layout, flat_colours: bool = False) -> None:
        self._p = _pybullet()
        self.layout = layout
        self.flat_colours = flat_colours
        self._client = self._p.connect(self._p.DIRECT)
        self._labels: dict[int, tuple[int, int]] = {}
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> "RoomRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._client is not None:
            self._p.disconnect(physicsClientId=self._client)
            self._client = None

    def _texture(self, name: str) -> int:
        return self._p.loadTexture(str(data_path() / name), physicsClientId=self._client)

    def _build(self) -> None:
        p, client = self._p, self._client
        floor = p.loadURDF(str(data_path() / FLOOR_FILE), useFixedBase=True, physicsClientId=client)
        p.changeVisualShape(floor, -1, textureUniqueId=self._texture(FLOOR_TEXTURE), physicsClientId=client)
        self._labels[floor] = (CLASS_NAMES.index("floor"), BACKGROUND_INSTANCE)

        wall_texture = self._texture(self.layout.wall_texture)
        span = 2 * ROOM_HALF_SIZE + WALL_THICKNESS
        for scale, position in (
            ((span, WALL_THICKNESS, WALL_HEIGHT), (0.0, ROOM_HALF_SIZE, WALL_HEIGHT / 2)),
            ((span, WALL_THICKNESS, WALL_HEIGHT), (0.0, -ROOM_HALF_SIZE, WALL_HEIGHT / 2)),
            ((WALL_THICKNESS, span, WALL_HEIGHT), (ROOM_HALF_SIZE, 0.0, WALL_HEIGHT / 2)),
            ((WALL_THICKNESS, span, WALL_HEIGHT), (-ROOM_HALF_SIZE, 0.0, WALL_HEIGHT / 2)),
        ):
            shape = p.createVisualShape(
                p.GEOM_MESH, fileName=str(data_path() / WALL_MESH), meshScale=scale, physicsClientId=client
            )
            wall = p.createMultiBody(0, -1, shape, basePosition=position, physicsClientId=client)
            p.changeVisualShape(
                wall, -1, textureUniqueId=wall_texture, rgbaColor=(*self.layout.wall_tint, 1.0), physicsClientId=client
            )
            self._labels[wall] = (CLASS_NAMES.index("wall"), BACKGROUND_INSTANCE)

        for instance_id, placement in enumerate(self.layout.bodies, start=1):
            body = self._place(placement)
            self._labels[body] = (ASSETS[placement.asset].class_id, instance_id)
        if self.flat_colours:
            self._flatten()

    def _flatten(self) -> None:
        """Replace every body's texture by one flat colour (fixed per body id, so per layout).

        A white texture is bound to every link and tinted by ``rgbaColor`` (which multiplies the texture).
        """
        import imageio.v2 as imageio

        p, client = self._p, self._client
        with tempfile.TemporaryDirectory() as folder:
            white = Path(folder) / "white.png"
            imageio.imwrite(white, np.full((4, 4, 3), 255, dtype=np.uint8))
            texture = p.loadTexture(str(white), physicsClientId=client)
        for body in self._labels:
            colour = (*np.random.default_rng(body).uniform(0.3, 0.9, 3).tolist(), 1.0)
            for link in range(-1, p.getNumJoints(body, physicsClientId=client)):
                p.changeVisualShape(body, link, textureUniqueId=texture, rgbaColor=colour, physicsClientId=client)

    def _place(self, placement: Placement) -> int:
        p, client = self._p, self._client
        asset = ASSETS[placement.asset]
        orientation = _orientation(p, asset, placement.yaw)
        body = _load(p, client, asset, placement.mesh_id, placement.scale, orientation)
        lo, hi = (np.asarray(v) for v in p.getAABB(body, physicsClientId=client))
        origin = np.asarray(p.getBasePositionAndOrientation(body, physicsClientId=client)[0])
        surface = self.layout.table_top if placement.support == "table" else 0.0
        lift = surface - origin[2] if asset.rests_on_origin else surface - lo[2]
        position = origin + np.array([placement.x - (lo[0] + hi[0]) / 2, placement.y - (lo[1] + hi[1]) / 2, lift])
        p.resetBasePositionAndOrientation(body, position.tolist(), orientation, physicsClientId=client)
        return body

    def render(self, c2w: np.ndarray, height: int, width: int, hfov_deg: float) -> RenderedView:
        """Render the view of OpenCV camera-to-world ``c2w`` ``[4, 4]`` at ``height`` x ``width``."""
        p = self._p
        _, _, rgba, zbuffer, seg = p.getCameraImage(
            width,
            height,
            viewMatrix=_column_major(gl_view_matrix(c2w)),
            projectionMatrix=_column_major(projection_matrix(height, width, hfov_deg)),
            renderer=p.ER_TINY_RENDERER,
            lightDirection=self.layout.light_direction,
            shadow=1,
            lightAmbientCoeff=AMBIENT,
            lightDiffuseCoeff=DIFFUSE,
            lightSpecularCoeff=SPECULAR,
            physicsClientId=self._client,
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3]
        seg = np.asarray(seg, dtype=np.int64).reshape(height, width)
        hit = seg >= 0
        depth = np.where(hit, zbuffer_to_depth(np.asarray(zbuffer).reshape(height, width)), 0.0)
        lut = np.empty((max(self._labels) + 2, 2), dtype=np.int64)
        lut[:] = (IGNORE_INDEX, BACKGROUND_INSTANCE)  # row 0 is seg -1: nothing hit
        for body, labels in self._labels.items():
            lut[body + 1] = labels
        labels = lut[np.clip(seg, -1, len(lut) - 2) + 1]
        return RenderedView(
            rgb=np.ascontiguousarray(rgb),
            depth=depth,
            semantic=labels[..., 0].astype(np.uint8),
            instance=labels[..., 1].astype(np.uint16),
        )
