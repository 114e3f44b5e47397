"""``python -m gpnerf_core data prepare-capture <video file | image folder> --out <scene> [options]``.

A phone video or a folder of photos to a posed capture, in four stages, each with a progress bar and its seconds in
the summary:

1. frames (``video_frames``): a video is decoded through imageio-ffmpeg and ``--frames N`` frames evenly spaced
   (default 100) or every ``--every N``-th are picked; a folder's images are taken in natural name order (all, or
   ``--frames`` / ``--every`` of them; every image the same size). Frames are downscaled to ``--max-size`` and the
   blurry ones dropped by ``video_frames.SHARPNESS_RULE``. At least ``video_frames.MIN_FRAMES`` must remain.
2. structure from motion (``sfm``): SIFT features with one camera for all frames (``--camera-model``, default
   SIMPLE_PINHOLE, or fixed ``--intrinsics fx,fy,cx,cy``), sequential matching (``--matcher exhaustive`` for photos
   not taken in order), incremental mapping, on ``--device``. Sequential is the default for folders too: on the
   embedded orbit (repeated floor and wall textures), exhaustive matching registered the frames with a normal
   reprojection error but poses off by a median 47 degrees, joining unrelated views of the same texture, while
   sequential matching was within 1.4 degrees (docs/datasets/capture.md); a wrong sequential result fails loudly
   (frames not registered), a wrong exhaustive one did not.
3. the registered-fraction check: under half of the frames registered in the largest model stops here (exit 2).
4. import (``colmap_import``): the largest model becomes ``transforms.json`` + ``images/``; the sparse models are kept
   in ``colmap/sparse/``.

Everything is built in a temporary folder beside ``--out`` and renamed into place at the end; a failure or Ctrl-C
deletes it and leaves ``--out`` as it was.
"""

from __future__ import annotations

import argparse
import math
import shutil
import time
from pathlib import Path
from typing import Any

from gpnerf_core import ArgumentParser, ConfigError, DataError
from gpnerf_plugins.datasets.capture import video_frames
from gpnerf_plugins.datasets.capture.colmap_import import (
    NEAR_FAR_RULE,
    TRANSFORMS_FILE,
    format_summary,
    import_model,
    write_transforms,
)
from gpnerf_plugins.datasets.capture.sfm import CAMERA_MODELS, DEVICES, MATCHERS, SfmOptions, run_sfm
from gpnerf_plugins.datasets.capture.staging import check_destination, staged

DEFAULT_MAX_SIZE = 640
SPARSE_DIR = "colmap/sparse"
HINT = (
    "more texture and overlap between frames, slower camera motion, or more frames (a smaller --every, a larger "
    "--frames) usually help; for photos not taken in order, --matcher exhaustive"
)


def parse_intrinsics(text: str | None) -> tuple[float, float, float, float] | None:
    """``"fx,fy,cx,cy"`` -> four positive finite floats (None for None)."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"--intrinsics {text}; expected four positive numbers fx,fy,cx,cy in pixels")
    return values  # type: ignore[return-value]


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog="gpnerf_core data prepare-capture",
        description="Turn a video or a folder of photos into a posed capture (transforms.json + images/) by structure "
        "from motion (pycolmap). Blurry frames: " + video_frames.SHARPNESS_RULE + ". Per-frame near/far: "
        + NEAR_FAR_RULE + ".",
    )
    parser.add_argument("source", type=Path, help="a video file (anything ffmpeg decodes) or a folder of images")
    parser.add_argument("--out", type=Path, required=True, help="the scene folder to write (new or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    picking = parser.add_mutually_exclusive_group()
    picking.add_argument("--frames", type=int, help=f"pick N frames evenly spaced (video default "
                         f"{video_frames.DEFAULT_VIDEO_FRAMES}; a folder keeps all its images)")
    picking.add_argument("--every", type=int, help="pick every N-th frame (or image)")
    parser.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE,
                        help=f"downscale so the longer side is at most this many pixels (default {DEFAULT_MAX_SIZE}; "
                        "0 keeps the size)")
    parser.add_argument("--sharpness", type=float, default=video_frames.DEFAULT_SHARPNESS,
                        help="drop a frame whose variance of the Laplacian is below this fraction of the median of "
                        f"the {video_frames.SHARPNESS_WINDOW} picked frames around it (default "
                        f"{video_frames.DEFAULT_SHARPNESS:g}; 0 keeps all)")
    parser.add_argument("--camera-model", choices=CAMERA_MODELS, default=None,
                        help="camera model structure from motion fits (default SIMPLE_PINHOLE)")
    parser.add_argument("--intrinsics", help="known fx,fy,cx,cy in pixels of the source frames (COLMAP convention: the "
                        "top-left pixel's centre is 0.5,0.5), held fixed; scaled with --max-size")
    parser.add_argument("--matcher", choices=MATCHERS, default="sequential",
                        help="sequential (default: frames in the order taken, each matched with its neighbours) or "
                        "exhaustive (every pair: photos not taken in order; it can join unrelated views of a "
                        "repeated texture into wrong poses)")
    parser.add_argument("--device", choices=DEVICES, default="auto", help="auto: CUDA where pycolmap has it")
    parser.add_argument("--threads", type=int, default=-1, help="CPU threads (default -1: all cores)")
    parser.add_argument("--seed", type=int, default=0, help="pycolmap's random seed (default 0)")
    parser.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    return parser


def _sfm_options(args: argparse.Namespace, frame_set: video_frames.FrameSet) -> SfmOptions:
    intrinsics = parse_intrinsics(args.intrinsics)
    if intrinsics is not None:
        if args.camera_model not in (None, "PINHOLE"):
            raise ConfigError(f"--camera-model {args.camera_model} with --intrinsics; expected --intrinsics alone "
                              "(it fixes a PINHOLE camera)")
        (width, height), (source_width, source_height) = frame_set.size, frame_set.source_size
        sx, sy = width / source_width, height / source_height
        intrinsics = (intrinsics[0] * sx, intrinsics[1] * sy, intrinsics[2] * sx, intrinsics[3] * sy)
    return SfmOptions(camera_model=args.camera_model or "SIMPLE_PINHOLE", intrinsics=intrinsics, matcher=args.matcher,
                      device=args.device, threads=args.threads, seed=args.seed, verbose=args.verbose)


def prepare_capture(args: argparse.Namespace, progress: bool | None = None) -> dict[str, Any]:
    """Run the four stages for parsed ``args``; returns the transforms.json content written to ``args.out``.

    Raises:
        ConfigError: a bad option value.
        DataError: bad input (named with the value), or structure from motion registering under half of the frames.
    """
    if args.max_size < 0:
        raise ConfigError(f"--max-size {args.max_size}; expected 0 (keep) or a positive number of pixels")
    if not 0 <= args.sharpness < 1:
        raise ConfigError(f"--sharpness {args.sharpness}; expected a fraction in [0, 1)")
    if args.threads == 0 or args.threads < -1:
        raise ConfigError(f"--threads {args.threads}; expected -1 (all cores) or a positive number")
    parse_intrinsics(args.intrinsics)
    source = Path(args.source).expanduser()
    out = check_destination(Path(args.out), overwrite=args.overwrite, inputs=[source])
    seconds: dict[str, float] = {}
    begin = time.perf_counter()
    with staged(out) as stage:
        frame_set = video_frames.load_frames(source, frames=args.frames, every=args.every, max_size=args.max_size,
                                             sharpness_fraction=args.sharpness, progress=progress)
        options = _sfm_options(args, frame_set)
        frames_dir = stage.scratch / "frames"
        sources = video_frames.write_frames(frame_set, frames_dir)
        seconds["frames"] = time.perf_counter() - begin

        sfm_dir = stage.scratch / "colmap"
        result = run_sfm(frames_dir, list(sources), sfm_dir, options, progress)
        seconds.update(result.seconds)
        given = len(sources)
        if 2 * result.best < given:
            raise DataError(
                f"{source}: structure from motion registered {result.best} of {given} frames in its largest model, "
                f"under half; {HINT}"
            )

        start = time.perf_counter()
        transforms = import_model(result.sparse, frames_dir, stage.scene, progress=progress,
                                  label=lambda path: path.relative_to(sfm_dir.parent).as_posix())
        shutil.copytree(result.sparse, stage.scene / SPARSE_DIR)
        seconds["import"] = time.perf_counter() - start
        seconds["total"] = time.perf_counter() - begin
        summary = transforms["gpnerf_summary"]
        summary.update(
            tool="prepare-capture",
            source=str(source),
            source_kind=frame_set.kind,
            source_total_frames=frame_set.total,
            source_size=list(frame_set.source_size),
            frame_size=list(frame_set.size),
            blurry_dropped=frame_set.blurry,
            sharpness_rule=video_frames.SHARPNESS_RULE,
            sharpness_fraction=args.sharpness,
            source_frames=sources,
            sfm={"camera_model": "PINHOLE (fixed)" if options.intrinsics else options.camera_model,
                 "intrinsics": list(options.intrinsics) if options.intrinsics else None, "matcher": options.matcher,
                 "device": options.device, "seed": options.seed, "registered_per_model": result.registered},
            seconds={key: round(value, 2) for key, value in seconds.items()},
        )
        write_transforms(stage.scene, transforms)
    return transforms


def main(argv: list[str]) -> int:
    """Entry point of ``data prepare-capture``: prints the summary and where the scene is."""
    args = build_parser().parse_args(argv)
    transforms = prepare_capture(args)
    summary = transforms["gpnerf_summary"]
    out = Path(args.out).expanduser().absolute()
    blurry = len(summary["blurry_dropped"])
    print(f"{summary['source_kind']} {summary['source']}: {summary['source_total_frames']} frames, "
          f"{summary['given_frames'] + blurry} picked, {blurry} blurry dropped, "
          f"{summary['frame_size'][0]}x{summary['frame_size'][1]} pixels, {summary['sfm']['matcher']} matching")
    print(format_summary(summary))
    print(f"wrote {out / TRANSFORMS_FILE}")
    return 0
