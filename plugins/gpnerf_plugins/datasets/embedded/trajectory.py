"""Smooth camera orbits (OpenCV camera-to-world poses) around a point of interest."""

from __future__ import annotations

import math

import numpy as np

RADIUS_RANGE = (1.2, 1.4)
"""Mean orbit radius (m) is drawn from this range; it then varies by +-RADIUS_SWING along the orbit."""
RADIUS_SWING = 0.1
HEIGHT_RANGE = (0.95, 1.15)
"""Mean camera height (m) above the floor; it varies by +-HEIGHT_SWING along the orbit."""
HEIGHT_SWING = 0.12
TARGET_JITTER = 0.08
"""Amplitude (m) of the smooth wander of the look-at point."""


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV camera-to-world ``[4, 4]`` of a camera at ``eye`` looking at ``target`` with no roll.

    OpenCV axes: x right, y down, z forward (into the scene).
    """
    forward = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def orbit(rng: np.random.Generator, num_frames: int, centre: tuple[float, float], focus_height: float) -> np.ndarray:
    """A closed orbit of ``num_frames`` cameras around ``centre`` looking near ``(centre, focus_height)``.

    Radius, height and look-at point vary smoothly (low-order sinusoids with random phases), so consecutive
    frames overlap well and the full circle shows every side of the objects.

    Returns:
        ``[num_frames, 4, 4]`` float64 OpenCV camera-to-world poses, metres.
    """
    start = rng.uniform(0, 2 * math.pi)
    direction = 1.0 if rng.uniform() < 0.5 else -1.0
    radius = rng.uniform(*RADIUS_RANGE)
    height = rng.uniform(*HEIGHT_RANGE)
    phases = rng.uniform(0, 2 * math.pi, size=5)
    poses = np.empty((num_frames, 4, 4))
    for k in range(num_frames):
        t = 2 * math.pi * k / num_frames
        angle = start + direction * t
        r = radius + RADIUS_SWING * math.sin(2 * t + phases[0])
        h = height + HEIGHT_SWING * math.sin(t + phases[1])
        eye = np.array([centre[0] + r * math.cos(angle), centre[1] + r * math.sin(angle), h])
        target = np.array([
            centre[0] + TARGET_JITTER * math.sin(t + phases[2]),
            centre[1] + TARGET_JITTER * math.cos(2 * t + phases[3]),
            focus_height + TARGET_JITTER * math.sin(3 * t + phases[4]),
        ])
        poses[k] = look_at(eye, target)
    return poses
