"""Pose sanity: cameras that do not fit the rest of their scene, and a camera scale that does not fit near/far.

``check_poses`` looks at a scene's cameras only (no image is read) and returns ``PoseFinding``s, each naming its frame
(a scale finding names the scene). The rules, in the order they run (``docs/datasets/pose_sanity.md`` explains what to
do about each):

- **outlier** (a warning): with ``d`` the distance of each camera centre to the per-coordinate median centre, ``m`` the
  median of ``d`` and ``MAD`` the median of ``|d - m|``, a camera is a candidate when
  ``d > max(m + OUTLIER_K * 1.4826 * MAD, OUTLIER_FLOOR * m)`` (the floor keeps the jitter of a tight cluster, whose MAD
  is near zero, from counting). A candidate is an outlier when no chain of cameras, each within ``CHAIN_GAP`` times the
  median nearest-neighbour spacing of the next, links it to a camera that is not a candidate: the far end of a long
  walk is a chain, a mis-registered frame is alone.
- **scale** (refuses training): the cameras that are not outliers are spread against the ray range: their median
  nearest-neighbour spacing is more than ``far`` (neighbouring views are farther apart than any ray reaches), or all of
  them lie within ``EXTENT_UNDER_NEAR * near`` of each other (no parallax at the nearest depth a ray samples). Both mean
  the poses are in other units than near/far. **scale** (a warning): the depth at which the cameras' optical axes meet
  (below) is beyond ``CONTENT_OUTSIDE * far`` or under ``near / CONTENT_OUTSIDE``. A scale finding suggests the factor
  that brings that depth (or, without one, half the cameras' extent) to ``sqrt(near * far)``: ``dataset.scale=<f>``
  (the capture dataset's option; it multiplies translations, depths and per-frame near/far). When there is a scale
  finding the two rules below are skipped: they measure in near/far, which do not fit, and would flag every frame.
- **isolated** (a warning): points on a ``GRID`` x ``GRID`` grid of the frame's pixels, at ``OVERLAP_DEPTHS`` depths
  spaced geometrically from near to far (or at the frame's depth where ``depths`` gives one), are projected into every
  other camera; the frame is isolated when none of them lands in front of another camera, within that camera's
  near..far, inside its image. No occlusion is modelled, so this only finds frames whose view volume meets no other.
- **looking away** (a warning): each camera's looked-at point is on its optical axis at its content depth (the frame's
  depth where given; else the median depth along its axis of the closest approaches to the other cameras' axes (pairs at
  least ``AXIS_MIN_ANGLE_DEG`` apart, in front of both cameras, missing each other by at most ``AXIS_MISS`` of the sum
  of the two depths); else the scene's median of those; else ``sqrt(near * far)``; clamped to near..far). A camera looks
  away when no other camera's looked-at point is in front of it and inside its image widened by ``LOOK_MARGIN`` of its
  size on every side.

Coordinates: ``c2w`` are OpenCV camera-to-world poses (x right, y down, z forward) in metres, ``intrinsics`` pinhole
matrices at ``height`` x ``width`` with pixel centres at integer coordinates (``gpnerf_core.types``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from kornia.geometry.camera import project_points as kornia_project_points
from kornia.geometry.linalg import transform_points
from torch import Tensor

from gpnerf_core.errors import DataError
from gpnerf_core.geometry.projection import project_points, world_to_camera

OUTLIER, ISOLATED, LOOKING_AWAY, SCALE = "outlier", "isolated", "looking_away", "scale"
KINDS = (OUTLIER, ISOLATED, LOOKING_AWAY, SCALE)

OUTLIER_K = 5.0
"""Robust deviations (MAD scaled by 1.4826 to a normal sigma) above the median distance to the median centre."""
OUTLIER_FLOOR = 2.0
"""A candidate outlier is also farther than this many times the median distance to the median centre."""
CHAIN_GAP = 5.0
"""Cameras closer than this many median nearest-neighbour spacings are linked (a walk stays one chain)."""
EXTENT_UNDER_NEAR = 0.01
"""All (non-outlier) cameras within this fraction of ``near`` of each other refuse the scale."""
CONTENT_OUTSIDE = 3.0
"""Optical axes meeting beyond this many times ``far``, or closer than ``near`` over it, warn about the scale."""
GRID = 5
"""Pixels per image side whose rays the overlap test follows."""
OVERLAP_DEPTHS = 4
"""Depths per pixel (geometric from near to far) of the overlap test when no frame depth is given."""
AXIS_MIN_ANGLE_DEG = 10.0
"""Optical axes closer than this (parallel or opposite) do not locate the content."""
AXIS_MISS = 0.25
"""Two axes meet when their closest approach is within this fraction of the sum of the two depths."""
LOOK_MARGIN = 0.5
"""The image is widened by this fraction of its width and height on every side for the looking-away test."""
NEAREST_FIRST = 8
"""The overlap test tries each frame's nearest cameras first, and every camera only for frames they do not see."""
PROJECTED_PER_CHUNK = 1_000_000
"""Point-camera pairs projected at once by the overlap test (bounds its memory to some 100 MB)."""


@dataclass(frozen=True)
class PoseFinding:
    """One thing pose sanity found.

    Attributes:
        kind: one of ``KINDS``.
        frame: the frame's name, or None for a finding about the whole scene (``scale``).
        message: one line: what was measured, the rule it broke and what to do.
        refuses: True when training on the scene is meaningless (a scale that makes near/far meaningless); else a
            warning to print before training.
        factor: for ``scale``, the suggested ``dataset.scale`` (None when none can be computed or for other kinds).
    """

    kind: str
    frame: str | None
    message: str
    refuses: bool = False
    factor: float | None = None

    def __str__(self) -> str:
        return self.message if self.frame is None else f"frame {self.frame}: {self.message}"


def check_poses(
    c2w: Tensor,
    intrinsics: Tensor,
    height: int,
    width: int,
    near: float | Tensor,
    far: float | Tensor,
    *,
    names: Sequence[str] | None = None,
    depths: Tensor | None = None,
) -> list[PoseFinding]:
    """Pose findings of one scene (the module docstring states the rules); empty when all is plausible.

    Args:
        c2w: ``[N, 4, 4]`` rigid OpenCV camera-to-world poses, metres (``rigid_transform_problem`` checks them first).
        intrinsics: ``[N, 3, 3]`` at ``height`` x ``width`` pixels.
        near, far: ray range in metres, one for the scene or ``[N]`` per frame.
        names: the frames' names as a user knows them (files, ids); default their indices.
        depths: optional ``[N]`` typical depth of each frame's content in metres (e.g. its depth map's median;
            0 = unknown), used instead of the near..far sweep and the axis estimate.

    Returns:
        findings ordered scale first, then by frame; fewer than two frames give none.

    Raises:
        DataError: a pose, intrinsic matrix, depth or bound that is not finite, or bounds not ``0 < near < far``
            (named by frame).
    """
    num = int(c2w.shape[0])
    names = [str(i) for i in range(num)] if names is None else [str(n) for n in names]
    if c2w.shape != (num, 4, 4) or intrinsics.shape != (num, 3, 3) or len(names) != num:
        raise ValueError(f"c2w {list(c2w.shape)}, intrinsics {list(intrinsics.shape)} and {len(names)} names: "
                         "expected [N, 4, 4], [N, 3, 3] and N names")
    near_t = torch.as_tensor(near, dtype=torch.float64).expand(num).clone()
    far_t = torch.as_tensor(far, dtype=torch.float64).expand(num).clone()
    depth_t = torch.zeros(num, dtype=torch.float64) if depths is None else depths.to(torch.float64).reshape(num)
    for what, values in (("camera pose", c2w.reshape(num, -1)), ("intrinsic matrix", intrinsics.reshape(num, -1)),
                         ("near/far", torch.stack([near_t, far_t], -1)), ("depth", depth_t[:, None])):
        bad = ~torch.isfinite(values).all(-1)
        if bool(bad.any()):
            raise DataError(f"frame {names[int(bad.nonzero()[0])]}: {what} is not finite; expected finite numbers")
    bad = ~((near_t > 0) & (far_t > near_t))
    if bool(bad.any()):
        index = int(bad.nonzero()[0])
        raise DataError(f"frame {names[index]}: near {float(near_t[index]):g}, far {float(far_t[index]):g}; "
                        "expected 0 < near < far")
    if num < 2:
        return []
    poses = c2w.to(torch.float64).clone()
    # Centred on the median camera so float precision follows the rig's size, not its distance from the origin.
    poses[:, :3, 3] -= poses[:, :3, 3].median(dim=0).values
    axis_depths = _axis_depths(poses[:, :3, 3], poses[:, :3, 2])
    rig = _Rig(poses, intrinsics.to(torch.float64), int(height), int(width), near_t, far_t, depth_t, axis_depths)

    outliers, outlier_notes = _outliers(rig)
    per_frame: list[list[PoseFinding]] = [[] for _ in range(num)]
    for index, note in outlier_notes.items():
        per_frame[index].append(PoseFinding(OUTLIER, names[index], note))
    scale = _scale(rig, outliers)
    if scale is None:
        for index in _isolated(rig).nonzero().flatten().tolist():
            per_frame[index].append(PoseFinding(ISOLATED, names[index], _ISOLATED_MESSAGE.format(
                near=_short(float(rig.near[index])), far=_short(float(rig.far[index])))))
        for index in _looking_away(rig).nonzero().flatten().tolist():
            per_frame[index].append(PoseFinding(LOOKING_AWAY, names[index], _LOOKING_AWAY_MESSAGE))
    return ([scale] if scale is not None else []) + [finding for found in per_frame for finding in found]


_ISOLATED_MESSAGE = (
    "isolated frame: no point of its view between near {near} m and far {far} m is in front of and inside any other "
    "camera; no source view can be drawn for it (check its pose, or drop the frame)"
)
_LOOKING_AWAY_MESSAGE = (
    "camera looking away: no other camera's looked-at point is in front of it within its widened field of view; "
    "its pose is probably turned (a flipped axis or an OpenGL pose read as OpenCV), or the frame shows nothing the "
    "others do"
)


@dataclass
class _Rig:
    c2w: Tensor  # [N, 4, 4] float64, centred
    intrinsics: Tensor  # [N, 3, 3] float64
    height: int
    width: int
    near: Tensor  # [N]
    far: Tensor  # [N]
    depths: Tensor  # [N], 0 = unknown
    axis_depths: Tensor  # [N], NaN = unknown (``_axis_depths``)

    @property
    def centres(self) -> Tensor:
        return self.c2w[:, :3, 3]

    @property
    def axes(self) -> Tensor:
        return self.c2w[:, :3, 2]

    def distances(self) -> Tensor:
        """``[N, N]`` distances between camera centres, the diagonal infinite."""
        dist = torch.cdist(self.centres, self.centres)
        return dist.fill_diagonal_(math.inf)


def _short(value: float) -> str:
    """Two significant digits, without an exponent (a value a user can type as an override)."""
    text = f"{value:.2g}"
    if "e" in text:
        text = f"{float(text):.12f}".rstrip("0").rstrip(".")
    return text


def _spacing(dist: Tensor) -> float:
    """Median nearest-neighbour distance of ``dist`` ``[M, M]`` (diagonal infinite), ignoring coincident cameras."""
    nearest = dist.min(dim=1).values
    positive = nearest[nearest > 0]
    return float(positive.median()) if positive.numel() else 0.0


def _components(linked: Tensor) -> Tensor:
    """Connected component label (smallest member index) of each node of the symmetric ``[N, N]`` bool graph."""
    num = linked.shape[0]
    labels = torch.arange(num)
    big = torch.full((num, num), num, dtype=labels.dtype)
    while True:
        spread = torch.where(linked, labels[None, :].expand(num, -1), big).min(dim=1).values
        new = torch.minimum(labels, spread)
        if torch.equal(new, labels):
            return labels
        labels = new


def _outliers(rig: _Rig) -> tuple[Tensor, dict[int, str]]:
    """``[N]`` bool outliers and their messages by index (rule in the module docstring)."""
    centres = rig.centres
    offsets = (centres - centres.median(dim=0).values).norm(dim=-1)
    median = float(offsets.median())
    mad = float((offsets - median).abs().median())
    threshold = max(median + OUTLIER_K * 1.4826 * mad, OUTLIER_FLOOR * median)
    candidates = offsets > threshold
    num = centres.shape[0]
    if not bool(candidates.any()):
        return candidates, {}
    dist = rig.distances()
    spacing = _spacing(dist)
    labels = _components(dist <= CHAIN_GAP * spacing)
    anchored = torch.zeros(num, dtype=torch.bool)
    anchored[labels[~candidates]] = True
    outliers = candidates & ~anchored[labels]
    notes = {}
    for index in outliers.nonzero().flatten().tolist():
        others = dist[index].clone()
        others[outliers] = math.inf
        notes[index] = (
            f"outlier camera: its centre is {_short(float(offsets[index]))} m from the median camera centre, beyond "
            f"{_short(threshold)} m (the larger of median {_short(median)} + {OUTLIER_K:g} x 1.4826 x MAD "
            f"{_short(mad)}, and {OUTLIER_FLOOR:g} x the median), and {_short(float(others.min()))} m from the "
            f"nearest other camera (median neighbour spacing {_short(spacing)} m); check its pose (a mis-registered "
            "frame) or drop the frame"
        )
    return outliers, notes


def _axis_depths(centres: Tensor, axes: Tensor) -> Tensor:
    """``[N]`` depth along each camera's optical axis where the other cameras' axes meet it (NaN where none do).

    For the axes ``p_i + t a_i`` and ``p_j + s a_j`` the closest approach has ``t = (c e - d) / (1 - c^2)`` and
    ``s = (e - c d) / (1 - c^2)`` with ``c = a_i . a_j``, ``d = a_i . (p_i - p_j)``, ``e = a_j . (p_i - p_j)``; all
    terms are ``[N, N]`` products of ``[N, 3]`` matrices.
    """
    cos = axes @ axes.T
    own = (axes * centres).sum(-1)  # a_i . p_i
    along_i = own[:, None] - axes @ centres.T  # a_i . (p_i - p_j)
    along_j = centres @ axes.T - own[None, :]  # a_j . (p_i - p_j)
    offset_sq = torch.cdist(centres, centres) ** 2
    denominator = 1.0 - cos**2
    crossing = denominator >= math.sin(math.radians(AXIS_MIN_ANGLE_DEG)) ** 2
    denominator = torch.where(crossing, denominator, torch.ones_like(denominator))
    t = (cos * along_j - along_i) / denominator
    s = (along_j - cos * along_i) / denominator
    # |(p_i - p_j) + t a_i - s a_j|^2 expanded
    miss_sq = offset_sq + t**2 + s**2 + 2 * t * along_i - 2 * s * along_j - 2 * t * s * cos
    meets = crossing & (t > 0) & (s > 0) & (miss_sq.clamp_min(0) <= (AXIS_MISS * (t + s)) ** 2)
    meets.fill_diagonal_(False)
    return torch.where(meets, t, torch.full_like(t, math.nan)).nanmedian(dim=1).values


def _scale(rig: _Rig, outliers: Tensor) -> PoseFinding | None:
    """The scene's scale finding, if any (rules in the module docstring)."""
    inliers = ~outliers
    if int(inliers.sum()) < 2:
        return None
    dist = rig.distances()[inliers][:, inliers]
    spacing = _spacing(dist)
    extent = float(torch.where(torch.isinf(dist), torch.zeros_like(dist), dist).max())
    near, far = float(rig.near[inliers].median()), float(rig.far[inliers].median())
    given = rig.depths[inliers]
    axis = rig.axis_depths[inliers]
    if bool((given > 0).any()):
        content, source = float(given[given > 0].median()), "the frames' depths put the content"
    elif bool(torch.isfinite(axis).any()):
        content, source = float(axis[torch.isfinite(axis)].median()), "the cameras' optical axes meet"
    else:
        content, source = None, ""
    where = f"; {source} about {_short(content)} m ahead" if content is not None else ""
    if spacing > far:
        found = f"neighbouring cameras are a median {_short(spacing)} m apart, more than far = {_short(far)} m{where}"
        refuses = True
    elif extent < EXTENT_UNDER_NEAR * near:
        found = (f"all {int(inliers.sum())} cameras lie within {_short(extent)} m of each other, under "
                 f"{EXTENT_UNDER_NEAR:g} x near = {_short(EXTENT_UNDER_NEAR * near)} m (no parallax){where}")
        refuses = True
    elif content is not None and not near / CONTENT_OUTSIDE <= content <= CONTENT_OUTSIDE * far:
        found = (f"{source} about {_short(content)} m ahead of the cameras, outside "
                 f"near / {CONTENT_OUTSIDE:g} .. {CONTENT_OUTSIDE:g} x far = {_short(near / CONTENT_OUTSIDE)} .. "
                 f"{_short(CONTENT_OUTSIDE * far)} m")
        refuses = False
    else:
        return None
    reference = content if content is not None else extent / 2
    factor = float(_short(math.sqrt(near * far) / reference)) if reference > 0 else None
    fix = (f"rescale the poses with dataset.scale={_short(factor)} (it brings that content to "
           f"sqrt(near x far) = {_short(math.sqrt(near * far))} m; the capture dataset's option, multiplying "
           "translations, depths and per-frame near/far), or set dataset.near/far in the poses' units"
           if factor is not None else "give the poses in metres, or set dataset.near/far in the poses' units")
    message = (f"implausible scale: {found}; the poses look like they are in other units than near/far: {fix} "
               "(the overlap and viewing-direction checks wait until the scale fits)")
    return PoseFinding(SCALE, None, message, refuses=refuses, factor=factor)


def _isolated(rig: _Rig) -> Tensor:
    """``[N]`` bool: frames none of whose grid points (near..far, or the frame's depth) another camera sees.

    Each frame is first tried against its ``NEAREST_FIRST`` nearest cameras; only the frames none of those sees are
    tried against every camera (so a few hundred frames cost a few hundred times the nearest few, not N squared).
    """
    num = rig.c2w.shape[0]
    steps = torch.linspace(0.0, 1.0, OVERLAP_DEPTHS, dtype=torch.float64)
    sweep = rig.near[:, None] * (rig.far / rig.near)[:, None] ** steps[None, :]  # [N, D]
    known = rig.depths > 0
    sweep[known] = rig.depths[known, None]
    coords = (torch.arange(GRID, dtype=torch.float64) + 0.5) / GRID
    v, u = torch.meshgrid(coords * rig.height - 0.5, coords * rig.width - 0.5, indexing="ij")
    pixels = torch.stack([u.flatten(), v.flatten(), torch.ones(GRID * GRID, dtype=torch.float64)], -1)  # [P, 3]
    rays = torch.einsum("nij,pj->npi", torch.linalg.inv(rig.intrinsics), pixels)  # camera z = 1
    camera_points = rays[:, :, None, :] * sweep[:, None, :, None]  # [N, P, D, 3]
    world = torch.einsum("nij,npdj->npdi", rig.c2w[:, :3, :3], camera_points) + rig.centres[:, None, None, :]
    world = world.reshape(num, -1, 3)  # [N, Q, 3]
    frames = torch.arange(num)
    nearest = rig.distances().topk(min(NEAREST_FIRST, num - 1), dim=1, largest=False).indices  # [N, M]
    seen = _seen(rig, world, frames, nearest)
    unseen = frames[~seen]
    if unseen.numel():
        everyone = frames[None, :].expand(len(unseen), -1)
        seen[unseen] = _seen(rig, world[unseen], unseen, everyone)
    return ~seen


def _seen(rig: _Rig, world: Tensor, frames: Tensor, cameras: Tensor) -> Tensor:
    """``[F]`` bool: whether any of ``cameras[f]`` (``[F, M]`` indices) other than frame ``frames[f]`` itself sees one
    of that frame's points ``world[f]`` (``[F, Q, 3]``): in front, within its near..far, inside its image."""
    w2c = world_to_camera(rig.c2w)
    result = torch.zeros(len(frames), dtype=torch.bool)
    per_frame = cameras.shape[1] * world.shape[1]
    chunk = max(1, PROJECTED_PER_CHUNK // max(per_frame, 1))
    for start in range(0, len(frames), chunk):
        part = slice(start, start + chunk)
        viewers = cameras[part]  # [F, M]
        points = transform_points(w2c[viewers], world[part][:, None].expand(-1, viewers.shape[1], -1, -1))
        z = points[..., 2]  # [F, M, Q]
        in_range = (z >= rig.near[viewers][..., None]) & (z <= rig.far[viewers][..., None])
        safe = torch.where(in_range[..., None], points, torch.ones_like(points))  # never divides by a zero depth
        pixels = kornia_project_points(safe, rig.intrinsics[viewers][:, :, None].expand(*z.shape, 3, 3))
        visible = in_range & _inside(pixels, rig.height, rig.width, 0.0)
        visible &= (viewers != frames[part][:, None])[..., None]
        result[part] = visible.flatten(1).any(1)
    return result


def _looking_away(rig: _Rig) -> Tensor:
    """``[N]`` bool: cameras in front of which no other camera's looked-at point lies (widened image)."""
    depth = rig.depths.clone()
    axis = rig.axis_depths
    unknown = depth <= 0
    depth[unknown] = axis[unknown]
    missing = ~torch.isfinite(depth)
    if bool(missing.any()):
        found = axis[torch.isfinite(axis)]
        fallback = found.median() if found.numel() else None
        depth[missing] = fallback if fallback is not None else (rig.near * rig.far)[missing].sqrt()
    depth = torch.minimum(torch.maximum(depth, rig.near), rig.far)
    looked_at = rig.centres + depth[:, None] * rig.axes
    pix, z = project_points(looked_at, rig.intrinsics, rig.c2w)  # [cameras, points]
    sees = (z > 0) & _inside(pix, rig.height, rig.width, LOOK_MARGIN)
    sees.fill_diagonal_(False)
    return ~sees.any(dim=1)


def _inside(pixels: Tensor, height: int, width: int, margin: float) -> Tensor:
    """Whether ``(u, v)`` pixels lie inside the image widened by ``margin`` of its size on every side."""
    u, v = pixels[..., 0], pixels[..., 1]
    return ((u >= -0.5 - margin * width) & (u <= width - 0.5 + margin * width)
            & (v >= -0.5 - margin * height) & (v <= height - 0.5 + margin * height))
