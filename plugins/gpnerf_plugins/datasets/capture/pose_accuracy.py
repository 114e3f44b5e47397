"""``python -m gpnerf_plugins.datasets.capture.pose_accuracy [options]``: how well ``data prepare-capture`` recovers
the poses of an embedded scene. A benchmark: nothing in the framework imports it.

It renders one embedded layout (``--frames`` views of ``--height`` x ``--width`` pixels along its closed orbit; cached
under ``GPNERF_CACHE``), runs prepare-capture on those frames (or the first ``--first`` of them: an arc, like photos of
one side) as an image folder or as an MP4 made from them (``--input``), with any other option passed on to it,
and scores every registered frame against the true camera after a similarity alignment (Umeyama's method, through
``pycolmap.estimate_sim3d``) of the estimated camera centres onto the true ones:

- rotation error: the angle of ``R_true^T R_align R_est``, degrees;
- translation error: the distance between the aligned and the true camera centre, relative to the camera extent
  (the largest distance between two true camera centres);
- the median and the worst of both, the registered fraction, the focal length's relative error, and the seconds of
  each prepare-capture stage.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from gpnerf_core import DataError
from gpnerf_plugins.datasets.capture.colmap_import import TRANSFORMS_FILE, load_pycolmap
from gpnerf_plugins.datasets.capture.prepare import build_parser, prepare_capture
from gpnerf_plugins.datasets.embedded import HFOV_DEG, SEQUENCE, SceneSetParams, ensure_generated
from gpnerf_plugins.datasets.embedded.writer import parse_pose

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def score_poses(true_c2w: np.ndarray, estimated_c2w: np.ndarray) -> dict[str, float]:
    """Pose errors of ``estimated_c2w`` against ``true_c2w`` after the similarity that best maps the estimated camera
    centres onto the true ones.

    Args:
        true_c2w, estimated_c2w: ``[N, 4, 4]`` camera-to-world poses of the same N >= 3 frames, OpenCV axes; the
            estimated ones in any world and scale.

    Returns:
        ``rotation_deg_median/max``, ``translation_rel_median/max`` (fractions of the camera extent), ``scale`` (of the
        alignment), ``extent`` (of the true centres, their units).
    """
    pycolmap = load_pycolmap()
    true_c2w, estimated_c2w = np.asarray(true_c2w, np.float64), np.asarray(estimated_c2w, np.float64)
    if len(true_c2w) < 3:
        raise DataError(f"{len(true_c2w)} registered frames; expected at least 3 to align the poses")
    alignment = pycolmap.estimate_sim3d(estimated_c2w[:, :3, 3], true_c2w[:, :3, 3])
    if alignment is None:
        raise DataError("the estimated camera centres admit no similarity alignment (collinear or coincident)")
    rotation, scale = alignment.rotation.matrix(), float(alignment.scale)
    centres = scale * estimated_c2w[:, :3, 3] @ rotation.T + alignment.translation
    relative = np.swapaxes(true_c2w[:, :3, :3], 1, 2) @ (rotation @ estimated_c2w[:, :3, :3])
    rotation_deg = np.degrees(Rotation.from_matrix(relative).magnitude())
    extent = float(pdist(true_c2w[:, :3, 3]).max())
    translation = np.linalg.norm(centres - true_c2w[:, :3, 3], axis=1) / extent
    return {
        "rotation_deg_median": float(np.median(rotation_deg)), "rotation_deg_max": float(rotation_deg.max()),
        "translation_rel_median": float(np.median(translation)), "translation_rel_max": float(translation.max()),
        "scale": scale, "extent": extent,
    }


def _source_index(source: int | str) -> int:
    """The embedded frame a capture frame came from: a video frame index, or the number in ``rgb_<i>.png``."""
    if isinstance(source, int):
        return source
    match = re.fullmatch(r"rgb_(\d+)\.png", source)
    if match is None:
        raise DataError(f"source frame {source!r}; expected rgb_<index>.png of an embedded scene")
    return int(match.group(1))


def write_video(frames: list[Path], path: Path, fps: int = 10) -> Path:
    """An H.264 MP4 of the PNG ``frames`` through imageio-ffmpeg (quality 8 of 10)."""
    import imageio.v2 as imageio

    with imageio.get_writer(path, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=1) as writer:
        for frame in frames:
            writer.append_data(imageio.imread(frame))
    return path


def measure(frames: int, height: int, width: int, seed: int, kind: str, extra: list[str], work: Path,
            first: int | None = None) -> dict[str, Any]:
    """Render, prepare (the first ``first`` frames, default all) and score one scene; returns the scores with the
    capture's summary figures."""
    params = SceneSetParams(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=frames, height=height,
                            width=width, seed=seed)
    sequence = ensure_generated(params) / params.scene_names("train")[0] / SEQUENCE
    truth = np.stack([parse_pose(row) for row in (sequence / "traj_w_c.txt").read_text().splitlines()])
    used = min(first or frames, frames)
    pngs = [sequence / "rgb" / f"rgb_{i}.png" for i in range(used)]
    if kind == "video":
        source = write_video(pngs, work / "scene.mp4")
        extra = ["--frames", str(used), *extra]
    elif used < frames:
        source = work / "frames"
        source.mkdir()
        for png in pngs:
            shutil.copyfile(png, source / png.name)
    else:
        source = sequence / "rgb"
    out = work / "capture"
    args = build_parser().parse_args([str(source), "--out", str(out), "--max-size", "0", *extra])
    transforms = prepare_capture(args)
    summary = transforms["gpnerf_summary"]
    origin = {name: _source_index(s) for name, s in summary["source_frames"].items()}
    indices = [origin[Path(f["file_path"]).name] for f in transforms["frames"]]
    estimated = np.stack([np.asarray(f["transform_matrix"]) @ OPENGL_TO_OPENCV for f in transforms["frames"]])
    scores = score_poses(truth[indices], estimated)
    true_focal = width / (2.0 * math.tan(math.radians(HFOV_DEG) / 2.0))
    focal = transforms.get("fl_x", transforms["frames"][0].get("fl_x"))
    return {
        "scene": {"frames": frames, "used": used, "height": height, "width": width, "seed": seed, "input": kind},
        "registered": summary["registered_frames"], "given": summary["given_frames"],
        "registered_fraction": summary["registered_frames"] / used,
        **scores,
        "focal_rel_error": abs(focal - true_focal) / true_focal,
        "mean_reprojection_error_px": summary["mean_reprojection_error_px"], "points": summary["points"],
        "matcher": summary["sfm"]["matcher"], "seconds": summary["seconds"], "capture": str(out / TRANSFORMS_FILE),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gpnerf_plugins.datasets.capture.pose_accuracy",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=40, help="views along the orbit (default 40)")
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--seed", type=int, default=0, help="the embedded scene set's seed (its layout and orbit)")
    parser.add_argument("--first", type=int, help="use only the first N frames of the orbit (an arc)")
    parser.add_argument("--input", choices=("folder", "video"), default="folder")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--keep", type=Path, help="work in this (new) folder and keep the capture")
    args, extra = parser.parse_known_args(argv)
    with tempfile.TemporaryDirectory(prefix="pose_accuracy-") as temporary:
        work = args.keep or Path(temporary)
        work.mkdir(parents=True, exist_ok=True)
        result = measure(args.frames, args.height, args.width, args.seed, args.input, extra, work, args.first)
    used = result["scene"]["used"]
    print(f"scene: {used} of {args.frames} orbit frames of {args.width}x{args.height}, seed {args.seed}, as "
          f"{args.input} ({result['matcher']} matching)")
    print(f"registered {result['registered']} of {used} ({100 * result['registered_fraction']:.0f}%)")
    print(f"rotation error: median {result['rotation_deg_median']:.3f} deg, worst {result['rotation_deg_max']:.3f} deg")
    print(f"translation error (of the {result['extent']:.2f} m camera extent): median "
          f"{100 * result['translation_rel_median']:.2f}%, worst {100 * result['translation_rel_max']:.2f}%")
    print(f"focal length error {100 * result['focal_rel_error']:.2f}%, reprojection "
          f"{result['mean_reprojection_error_px']:.3f} px, {result['points']} points")
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result["seconds"].items()))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
