"""``python -m gpnerf_core data import-colmap <sparse model> --images <dir> --out <scene> [--overwrite]``.

Turns a COLMAP sparse model (binary or text, read through pycolmap) and its images into the capture layout
(``transforms.json`` plus ``images/``; docs/datasets/capture.md):

- Model: ``<sparse model>`` is a model folder (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``), or a
  folder holding several (``sparse/0``, ``sparse/1``, ...), or the project folder above ``sparse/``. Of several, the
  one with the most registered images is imported (ties: more points); the others are reported.
- Poses: COLMAP's world-to-camera (OpenCV axes) becomes camera-to-world in the OpenGL convention, as nerfstudio
  writes it: ``c2w = inverse(w2c)``, then the camera's y and z axes are negated. The world is COLMAP's (no
  ``applied_transform``).
- Cameras: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are written as ``PINHOLE``; ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV``
  as ``OPENCV`` (``k1 k2 p1 p2``; the reader undistorts), images copied byte for byte. Every other model (fisheye,
  ``FULL_OPENCV``, ...) has its images undistorted by pycolmap's ``undistort_image`` and is written as ``PINHOLE``
  (PNG images, the undistorted size). ``cx, cy`` keep COLMAP's convention (top-left pixel centre at 0.5, 0.5).
- Near/far (``NEAR_FAR_RULE``): per frame, from the depths (camera z) of the sparse points that frame observes.
- Sparse points: the chosen model's 3D points with their colours, written as ``sparse_points.ply`` (pycolmap's
  ``export_PLY``, COLMAP's world as the poses) and named by ``ply_file_path`` as nerfstudio does: what a per-scene
  Gaussian family starts from (``Scene.sparse_points``). A model without points writes none.
- Frames: the registered images of the chosen model, sorted by file name; images not registered, registered only in
  another model, or missing from ``--images`` are dropped and listed with the reason.
- Summary (printed and stored in ``transforms.json`` under ``gpnerf_summary``): registered / given frames (given: the
  images in ``--images`` and in the models), mean reprojection error, points, the camera models, what was dropped.

The user's files are only read. The scene is built in a temporary folder beside ``--out`` and renamed into place;
a non-empty ``--out`` is refused unless ``--overwrite``.
"""

from __future__ import annotations

import re
import shutil
import struct
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import numpy as np
from PIL import Image
from tqdm import tqdm

from gpnerf_core import ArgumentParser, ConfigError, DataError, atomic_write_json
from gpnerf_plugins.datasets.capture.staging import check_destination, staged
from gpnerf_plugins.datasets.common.image_io import decode_image, image_size, one_line_error

TRANSFORMS_FILE = "transforms.json"
IMAGES_DIR = "images"
POINTS_FILE = "sparse_points.ply"
MODEL_FILES = ("cameras", "images", "points3D")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")

NEAR_PERCENTILE, FAR_PERCENTILE = 1.0, 99.0
DEPTH_MARGIN = 0.1
MIN_POINTS = 8
NEAR_FAR_RULE = (
    f"near = {1 - DEPTH_MARGIN:g} x the {NEAR_PERCENTILE:g}st percentile and far = {1 + DEPTH_MARGIN:g} x the "
    f"{FAR_PERCENTILE:g}th percentile of the depths (camera z, model units) of the sparse points the frame observes; "
    f"a frame observing fewer than {MIN_POINTS} points takes the smallest near and the largest far of the others"
)

EXACT_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""COLMAP camera models the capture layout holds exactly (as PINHOLE or OPENCV); others are undistorted."""



def load_pycolmap() -> Any:
    """The ``pycolmap`` module, imported on first use (listing the data tools does not need it).

    Importing it installs glog's SIGTERM handler (a native stack dump, then death, with no ``finally`` run); the
    Python handler in place before (the command line's: SIGTERM unwinds as an exception) is put back."""
    import signal
    import threading

    previous = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    try:
        import pycolmap
    except ImportError as exc:
        raise ConfigError(
            f"pycolmap is not importable ({exc}); expected it installed: pip install 'pycolmap>=4.2'"
        ) from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return pycolmap


def natural_key(text: str) -> tuple[Any, ...]:
    """Sort key putting ``img_2`` before ``img_10`` (digit runs compare as numbers)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text))


def is_model(folder: Path) -> bool:
    """Whether ``folder`` holds a COLMAP sparse model (all of cameras, images, points3D as .bin, or all as .txt)."""
    return any(all((folder / f"{name}.{ext}").is_file() for name in MODEL_FILES) for ext in ("bin", "txt"))


def find_models(path: Path) -> list[Path]:
    """The model folders ``path`` names: itself, else its model subfolders, else those of ``path/sparse``."""
    expected = (
        "expected a COLMAP sparse model folder (cameras, images, points3D as .bin or .txt) or the folder holding "
        "several (sparse/0, sparse/1, ...)"
    )
    if not path.exists():
        raise DataError(f"{path}: not found; {expected}")
    if not path.is_dir():
        raise DataError(f"{path}: is a file; {expected}")
    if is_model(path):
        return [path]
    for parent in (path, path / "sparse"):
        if parent.is_dir():
            models = [c for c in parent.iterdir() if c.is_dir() and is_model(c)]
            if models:
                return sorted(models, key=lambda c: natural_key(c.name))
    raise DataError(f"{path}: no sparse model in it or in its subfolders; {expected}")


def _known_models(pycolmap: Any) -> dict[str, int]:
    return {name: int(m.value) for name, m in pycolmap.CameraModelId.__members__.items() if int(m.value) >= 0}


def unknown_camera_model(folder: Path, pycolmap: Any) -> str | None:
    """A one-line message naming the first camera whose model pycolmap does not know, or None.

    Reads ``cameras.bin`` when present (pycolmap prefers it), else ``cameras.txt``.
    """
    known = _known_models(pycolmap)
    expected = f"expected a COLMAP camera model ({', '.join(known)})"
    binary, text = folder / "cameras.bin", folder / "cameras.txt"
    if binary.is_file():
        data = binary.read_bytes()
        try:
            (count,), offset = struct.unpack_from("<Q", data), 8
            for _ in range(count):
                camera_id, model_id, _, _ = struct.unpack_from("<iiQQ", data, offset)
                if model_id not in known.values():
                    ids = f"ids 0-{max(known.values())}"
                    return f"{binary}: camera {camera_id} has model id {model_id}; {expected} ({ids})"
                camera = pycolmap.Camera.create_from_model_id(0, pycolmap.CameraModelId(model_id), 1.0, 1, 1)
                offset += 24 + 8 * camera.params.size
        except struct.error:
            return None
    elif text.is_file():
        for line in text.read_text(errors="replace").splitlines():
            fields = line.split()
            if fields and not fields[0].startswith("#") and len(fields) > 1 and fields[1] not in known:
                return f"{text}: camera {fields[0]} has model {fields[1]!r}; {expected}"
    return None


def read_model(folder: Path) -> Any:
    """``pycolmap.Reconstruction`` of one model folder; a malformed one is a one-line ``DataError`` naming it."""
    pycolmap = load_pycolmap()
    try:
        return pycolmap.Reconstruction(folder)
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError carrying a C++ check message
        unknown = unknown_camera_model(folder, pycolmap)
        if unknown is not None:
            raise DataError(unknown) from None
        raise DataError(
            f"{folder}: unreadable COLMAP model ({one_line_error(exc)}); expected cameras, images and points3D "
            "as COLMAP writes them"
        ) from None


def opengl_camera_to_world(cam_from_world: np.ndarray) -> np.ndarray:
    """COLMAP's ``[3, 4]`` world-to-camera (OpenCV axes) -> ``[4, 4]`` camera-to-world with OpenGL axes
    (x right, y up, z backward): the inverse, then its y and z columns negated."""
    w2c = np.eye(4)
    w2c[:3] = cam_from_world
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1
    return c2w


def camera_keys(camera: Any) -> dict[str, Any] | None:
    """transforms.json intrinsics of a COLMAP camera of one of ``EXACT_MODELS`` (None for any other model)."""
    name, p = camera.model.name, [float(v) for v in camera.params]
    keys: dict[str, Any] = {"w": int(camera.width), "h": int(camera.height)}
    if name == "SIMPLE_PINHOLE":
        keys.update(camera_model="PINHOLE", fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2])
    elif name == "PINHOLE":
        keys.update(camera_model="PINHOLE", fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3])
    elif name == "SIMPLE_RADIAL":
        keys.update(camera_model="OPENCV", fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2], k1=p[3], k2=0.0, p1=0.0, p2=0.0)
    elif name == "RADIAL":
        keys.update(camera_model="OPENCV", fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2], k1=p[3], k2=p[4], p1=0.0, p2=0.0)
    elif name == "OPENCV":
        keys.update(camera_model="OPENCV", fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    else:
        return None
    return keys


def depth_bounds(depths: np.ndarray) -> tuple[float, float] | None:
    """``(near, far)`` by ``NEAR_FAR_RULE`` from the depths of one frame's points; None with under ``MIN_POINTS``."""
    depths = depths[np.isfinite(depths) & (depths > 0)]
    if depths.size < MIN_POINTS:
        return None
    low, high = np.percentile(depths, [NEAR_PERCENTILE, FAR_PERCENTILE])
    return float((1 - DEPTH_MARGIN) * low), float((1 + DEPTH_MARGIN) * high)


def observed_depths(reconstruction: Any, image: Any) -> np.ndarray:
    """Depths (camera z, model units) of the 3D points ``image`` observes."""
    ids = [point.point3D_id for point in image.get_observation_points2D()]
    if not ids:
        return np.zeros(0)
    xyz = np.array([reconstruction.point3D(i).xyz for i in ids], dtype=np.float64)
    w2c = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    return xyz @ w2c[2, :3] + w2c[2, 3]


def image_files(folder: Path) -> list[str]:
    """Image files under ``folder`` (hidden folders skipped), as paths relative to it, in natural order."""
    names = []
    for path in folder.rglob("*"):
        relative = path.relative_to(folder)
        hidden = any(part.startswith(".") for part in relative.parts)
        if path.suffix.lower() in IMAGE_SUFFIXES and path.is_file() and not hidden:
            names.append(relative.as_posix())
    return sorted(names, key=natural_key)


class _Undistorter:
    """pycolmap's undistortion of one camera to PINHOLE (what ``undistort_image`` returns, computed once)."""

    def __init__(self, camera: Any, pycolmap: Any) -> None:
        self.camera, self.pycolmap = camera, pycolmap
        self.options = pycolmap.UndistortCameraOptions()
        self.keys = camera_keys(pycolmap.undistort_camera(self.options, camera))

    def write(self, source: Path, target: Path) -> None:
        rgb = np.asarray(decode_image(source, "an image file").convert("RGB"))
        bitmap, _ = self.pycolmap.undistort_image(self.options, self.pycolmap.Bitmap.from_array(rgb), self.camera)
        Image.fromarray(bitmap.to_array()).save(target, format="PNG")


def _check_size(path: Path, camera: Any) -> None:
    height, width = image_size(path, "an image file")
    if (width, height) != (camera.width, camera.height):
        raise DataError(
            f"{path}: {width}x{height} pixels; camera {camera.camera_id} ({camera.model.name}) of the model is "
            f"{camera.width}x{camera.height}; expected the images the model was made from"
        )


def drop_reasons(
    files: set[str], in_models: set[str], registered: set[str], elsewhere: dict[str, str]
) -> dict[str, str]:
    """Why each given image (a file in --images or an image of a model) is not imported, by name in natural order.

    Args:
        files: image files in --images; in_models: images of any model; registered: registered in the chosen model;
        elsewhere: registered only in another model, with that model's label.
    """
    reasons = {}
    for name in sorted(files | in_models, key=natural_key):
        if name in registered:
            if name not in files:
                reasons[name] = "image file missing from --images"
        elif name in elsewhere:
            reasons[name] = f"registered only in the smaller model {elsewhere[name]}"
        elif name in in_models:
            reasons[name] = "in the model but not registered"
        else:
            reasons[name] = "not in the model (structure from motion did not register it)"
    return reasons


def _choose(model_paths: list[Path]) -> tuple[int, list[Any]]:
    reconstructions = [read_model(path) for path in model_paths]
    scores = [(r.num_reg_images(), r.num_points3D()) for r in reconstructions]
    return max(range(len(scores)), key=lambda i: (scores[i], -i)), reconstructions


def import_model(model: Path, images: Path, scene: Path, *, progress: bool | None = None,
                 label: Callable[[Path], str] = str) -> dict[str, Any]:
    """Write ``scene/images/`` and return the transforms.json content (``gpnerf_summary`` included).

    Args:
        model: a model folder or a folder of models (``find_models``).
        images: the folder the model's image names are relative to.
        scene: an empty folder to write into.
        progress: show a tqdm bar (None: only on a terminal).
        label: how the summary names a model folder.

    Raises:
        DataError: no model, an unreadable one, an image missing, of the wrong size or undecodable, a non-finite pose,
            or no registered frame whose image exists.
    """
    pycolmap = load_pycolmap()
    model_paths = find_models(model)
    chosen, reconstructions = _choose(model_paths)
    reconstruction, chosen_path = reconstructions[chosen], model_paths[chosen]
    registered = {reconstruction.image(i).name: i for i in reconstruction.reg_image_ids()}
    elsewhere = {}
    for path, other in zip(model_paths, reconstructions):
        if other is not reconstruction:
            for i in other.reg_image_ids():
                elsewhere.setdefault(other.image(i).name, label(path))
    in_models = {image.name for r in reconstructions for image in r.images.values()}
    files = set(image_files(images))
    dropped = drop_reasons(files, in_models, set(registered), elsewhere)
    names = sorted((n for n in registered if n not in dropped), key=natural_key)
    if not names:
        raise DataError(
            f"{images}: none of the {len(registered)} registered images of {chosen_path} is here; expected --images "
            "to be the folder the model's image names are relative to"
        )

    exact = {name: camera_keys(reconstruction.image(registered[name]).camera) is not None for name in names}
    targets = {name: Path(IMAGES_DIR, name if exact[name] else Path(name).with_suffix(".png")).as_posix()
               for name in names}
    clashes = [target for target, count in Counter(targets.values()).items() if count > 1]
    if clashes:
        raise DataError(
            f"{images}: several images would be written as {clashes[0]} (undistorted images are saved as PNG); "
            "expected distinct file names apart from the extension"
        )

    undistorters: dict[int, _Undistorter] = {}
    frames, bounds = [], {}
    for name in tqdm(names, desc="import", unit="frame", disable=None if progress is None else not progress):
        image = reconstruction.image(registered[name])
        camera, source, relative = image.camera, images / name, targets[name]
        _check_size(source, camera)
        (scene / relative).parent.mkdir(parents=True, exist_ok=True)
        if exact[name]:
            keys = camera_keys(camera)
            shutil.copyfile(source, scene / relative)
        else:
            undistorter = undistorters.get(image.camera_id)
            if undistorter is None:
                undistorter = undistorters[image.camera_id] = _Undistorter(camera, pycolmap)
            undistorter.write(source, scene / relative)
            keys = undistorter.keys
        c2w = opengl_camera_to_world(np.asarray(image.cam_from_world().matrix(), dtype=np.float64))
        if not np.isfinite(c2w).all():
            raise DataError(
                f"{chosen_path}: image {name} has a non-finite pose; expected a finite rotation and translation"
            )
        frame_bounds = depth_bounds(observed_depths(reconstruction, image))
        if frame_bounds is not None:
            bounds[relative] = frame_bounds
        frames.append({"file_path": relative, "transform_matrix": c2w.tolist(), "colmap_im_id": int(image.image_id),
                       **keys})

    scene_bounds = None
    if bounds:
        scene_bounds = (min(b[0] for b in bounds.values()), max(b[1] for b in bounds.values()))
        for frame in frames:
            frame["near"], frame["far"] = bounds.get(frame["file_path"], scene_bounds)
    frames.sort(key=lambda f: f["file_path"])
    transforms: dict[str, Any] = {"frames": frames}
    if reconstruction.num_points3D():
        reconstruction.export_PLY(str(scene / POINTS_FILE))
        transforms["ply_file_path"] = POINTS_FILE
    shared = _shared_intrinsics(frames)
    transforms.update(shared)
    for frame in frames:
        for key in shared:
            del frame[key]

    others = [{"model": label(path), "registered_frames": r.num_reg_images(), "points": r.num_points3D()}
              for path, r in zip(model_paths, reconstructions) if r is not reconstruction]
    transforms["gpnerf_summary"] = {
        "tool": "import-colmap",
        "model": label(chosen_path),
        "other_models": others,
        "given_frames": len(files | in_models),
        "registered_frames": len(frames),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "points": int(reconstruction.num_points3D()),
        "colmap_camera_models": dict(Counter(reconstruction.image(registered[n]).camera.model.name for n in names)),
        "undistorted": bool(undistorters),
        "near_far_rule": NEAR_FAR_RULE,
        "near_far_from_other_frames": sorted(f["file_path"] for f in frames if bounds and f["file_path"] not in bounds),
        "near_far_written": scene_bounds is not None,
        "dropped": [{"frame": name, "reason": reason} for name, reason in dropped.items()],
    }
    return transforms


def _shared_intrinsics(frames: list[dict[str, Any]]) -> dict[str, Any]:
    """The camera keys every frame has with the same value (written once at the top level)."""
    keys = ("camera_model", "w", "h", "fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")
    first = frames[0]
    return {k: first[k] for k in keys if k in first and all(k in f and f[k] == first[k] for f in frames)}


def write_transforms(scene: Path, transforms: dict[str, Any]) -> Path:
    """Write ``scene/transforms.json`` (a NaN anywhere is refused by the atomic writer)."""
    return atomic_write_json(scene / TRANSFORMS_FILE, transforms)


def format_summary(summary: dict[str, Any], limit: int = 5) -> str:
    """The summary as printed: a few lines, the dropped frames' first ``limit`` names with their reasons."""
    others = ", ".join(f"{o['model']} ({o['registered_frames']} frames)" for o in summary["other_models"])
    lines = [
        f"registered {summary['registered_frames']} of {summary['given_frames']} frames from {summary['model']}"
        + (f"; other models, not imported: {others}" if others else ""),
        f"mean reprojection error {summary['mean_reprojection_error_px']:.3f} px, {summary['points']} points",
        "cameras: " + ", ".join(f"{k} x{v}" for k, v in summary["colmap_camera_models"].items())
        + ("; images undistorted to PINHOLE" if summary["undistorted"] else ""),
    ]
    if summary["near_far_written"]:
        borrowed = len(summary["near_far_from_other_frames"])
        lines.append(f"near/far: {summary['near_far_rule']}" + (f" ({borrowed} such frames)" if borrowed else ""))
    else:
        lines.append(f"near/far: not written (no frame observes {MIN_POINTS} or more sparse points)")
    dropped = summary["dropped"]
    if dropped:
        shown = "; ".join(f"{d['frame']} ({d['reason']})" for d in dropped[:limit])
        more = ""
        if len(dropped) > limit:
            more = f"; and {len(dropped) - limit} more (transforms.json, gpnerf_summary.dropped)"
        lines.append(f"dropped {len(dropped)}: {shown}{more}")
    if "seconds" in summary:
        lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in summary["seconds"].items()))
    return "\n".join(lines)


def import_colmap(model: Path, images: Path, out: Path, *, overwrite: bool = False,
                  progress: bool | None = None) -> dict[str, Any]:
    """Import ``model`` with its ``images`` into the new scene folder ``out``; returns the transforms.json content."""
    images, model = Path(images).expanduser(), Path(model).expanduser()
    if not images.is_dir():
        raise DataError(f"--images {images}: not a folder; expected the folder the model's image names are relative to")
    out = check_destination(Path(out), overwrite=overwrite, inputs=[images, model])
    if images.resolve() in out.resolve().parents:  # its images would count as the user's on the next import
        raise DataError(f"--out {out}: inside --images {images}; expected a folder outside it")
    with staged(out) as stage:
        transforms = import_model(model, images, stage.scene, progress=progress)
        write_transforms(stage.scene, transforms)
    return transforms


def main(argv: list[str]) -> int:
    """Entry point of ``data import-colmap``: imports, prints the summary and where the scene is."""
    parser = ArgumentParser(
        prog="gpnerf_core data import-colmap",
        description="Turn a COLMAP sparse model and its images into a capture (transforms.json + images/). "
        f"Per-frame near/far: {NEAR_FAR_RULE}.",
    )
    parser.add_argument("model", type=Path, help="a sparse model folder (e.g. sparse/0) or the folder holding several "
                        "(the one with the most registered images is imported)")
    parser.add_argument("--images", type=Path, required=True, help="the folder the model's image names are relative to")
    parser.add_argument("--out", type=Path, required=True, help="the scene folder to write (new or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    args = parser.parse_args(argv)
    out = Path(args.out).expanduser().absolute()
    transforms = import_colmap(args.model, args.images, out, overwrite=args.overwrite)
    print(format_summary(transforms["gpnerf_summary"]))
    print(f"wrote {out / TRANSFORMS_FILE}")
    return 0
