"""``python -m gpnerf_core data prepare-scannet <scan folder> [--out <root>] [--frame-skip N] [--overwrite]``.

Turns one ScanNet scan as downloaded (``<scan>/<scan>.sens`` and ``<scan>/<scan>_2d-label-filt.zip``) into the
layout ``ScanNetScenes`` reads (``scannet.files``): ``<out>/<scan>/{color,depth,label-filt,pose,intrinsic}``, plus
``instance-filt`` when ``<scan>/<scan>_2d-instance-filt.zip`` is there too (optional: without it nothing is written
for instances). Colour JPEGs, label and instance PNGs are copied as stored; depth is written as uint16 millimetre PNGs;
poses as 4 rows of 4 numbers (invalid ones stay ``-inf`` and the loader drops them). The scene is written into a
temporary folder beside the destination and renamed into place at the end, so an error leaves nothing half-written.
"""

from __future__ import annotations

import io
import os
import re
import shutil
import tempfile
import zipfile
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from gpnerf_core import ArgumentParser, ConfigError, DataError
from gpnerf_plugins.datasets.scannet.files import (
    COLOR_DIR,
    DEPTH_DIR,
    DEPTH_SCALE,
    INSTANCE_DIR,
    INTEGER_MODES,
    INTRINSIC_COLOR,
    LABEL_DIR,
    POSE_DIR,
    SCENE_NAME,
)
from gpnerf_plugins.datasets.scannet.labels import LABEL_MAP_NAME, LABEL_MAP_SOURCE
from gpnerf_plugins.datasets.scannet.sens import SensFrame, SensReader

DEFAULT_OUT = "data/scannet"


@dataclass(frozen=True)
class PrepareResult:
    """What ``prepare_scan`` wrote: ``frames`` frame folders' worth of files into ``folder``."""

    scene: str
    folder: Path
    frames: int
    total_frames: int
    invalid_poses: int
    instances: bool = False
    """Whether ``instance-filt/`` was written (the scan had ``_2d-instance-filt.zip``)."""


def _matrix_text(matrix: np.ndarray) -> str:
    """4 rows of 4 numbers; ``%.9g`` round-trips float32 exactly, ``-inf`` stays ``-inf``."""
    return "".join(" ".join(f"{float(v):.9g}" for v in row) + "\n" for row in matrix)


@dataclass(frozen=True)
class _ImageZip:
    """One of ScanNet's 2D zips (``_2d-label-filt.zip``, ``_2d-instance-filt.zip``), opened.

    ``folder`` is both the entries' folder inside (``<folder>/<n>.png``) and the scene folder they are written to.
    """

    archive: zipfile.ZipFile
    path: Path
    folder: str

    def entries(self) -> dict[int, zipfile.ZipInfo]:
        """The ``<folder>/<n>.png`` entries by frame number ``n``."""
        pattern = re.compile(rf"(?:^|/){re.escape(self.folder)}/(\d+)\.png$")
        entries: dict[int, zipfile.ZipInfo] = {}
        for info in self.archive.infolist():
            match = pattern.search(info.filename)
            if match is None:
                continue
            number = int(match.group(1))
            if number in entries:
                raise DataError(
                    f"{self.path}: {info.filename} and {entries[number].filename} are both frame {number}; "
                    "expected one image per frame"
                )
            entries[number] = info
        if not entries:
            expected = f"expected ScanNet's _2d-{self.folder}.zip"
            raise DataError(f"{self.path}: no {self.folder}/<frame>.png inside; {expected}")
        return entries

    def frame_entries(self, reader: SensReader) -> dict[int, zipfile.ZipInfo]:
        """``entries()``, checked to be exactly one per frame ``0..N-1`` of the ``.sens`` stream."""
        entries, frames = self.entries(), reader.header.num_frames
        if len(entries) != frames:
            raise DataError(
                f"{self.path}: {len(entries)} {self.folder} images for {frames} frames in {reader.path}; "
                f"expected one {self.folder} image per frame"
            )
        absent = sorted(set(range(frames)) - set(entries))
        if absent:
            raise DataError(
                f"{self.path}: no {self.folder}/{absent[0]}.png; "
                f"expected {self.folder} images for frames 0..{frames - 1}"
            )
        return entries

    def png(self, info: zipfile.ZipInfo) -> bytes:
        """The entry's bytes as stored, after checking they are a complete single-channel integer PNG."""
        try:
            data = self.archive.read(info)
            with Image.open(io.BytesIO(data)) as image:
                fmt, mode = image.format, image.mode
                image.verify()
        except Exception as exc:
            raise DataError(f"{self.path}: {info.filename} is unreadable ({type(exc).__name__}: {exc})") from None
        if fmt != "PNG" or mode not in INTEGER_MODES:
            raise DataError(
                f"{self.path}: {info.filename} is a {fmt} of mode {mode}; expected a single-channel integer PNG"
            )
        return data


def _open_zip(stack: ExitStack, path: Path, folder: str) -> _ImageZip:
    """Open ``path`` for the rest of ``stack``; a file that is not a zip is a one-line ``DataError`` naming it."""
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise DataError(f"{path}: not a readable zip archive ({exc})") from None
    return _ImageZip(stack.enter_context(archive), path, folder)


def _check_jpeg(data: bytes, reader: SensReader, index: int) -> None:
    header = reader.header
    try:
        with Image.open(io.BytesIO(data)) as image:
            fmt, size = image.format, image.size
    except Exception as exc:
        raise DataError(f"{reader.path}: colour of frame {index} is not a readable image ({exc})") from None
    if fmt != "JPEG" or size != (header.color_width, header.color_height):
        raise DataError(
            f"{reader.path}: colour of frame {index} is a {size[0]}x{size[1]} {fmt}; "
            f"expected a {header.color_width}x{header.color_height} JPEG as the header says"
        )


def _depth_millimetres(reader: SensReader, frame: SensFrame) -> np.ndarray:
    depth = reader.depth_image(frame)
    shift = reader.header.depth_shift
    if shift == DEPTH_SCALE:
        return depth
    scaled = np.rint(depth.astype(np.float64) * (DEPTH_SCALE / shift))
    return np.clip(scaled, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _write_scene(folder: Path, reader: SensReader, zips: list[_ImageZip], every: int) -> tuple[int, int]:
    """Write the layout into ``folder``; returns ``(frames written, of which with an invalid pose)``.

    ``zips``: the label zip, then the instance zip if the scan has one; each frame's PNG of each is copied.
    """
    header = reader.header
    entries = [(image_zip, image_zip.frame_entries(reader)) for image_zip in zips]
    if header.color_compression != "jpeg":
        raise DataError(f"{reader.path}: colour compression {header.color_compression}; expected jpeg (ScanNet's)")
    if not np.isfinite(header.depth_shift) or header.depth_shift <= 0:
        raise DataError(
            f"{reader.path}: depth shift {header.depth_shift}; expected a positive number (1000 in ScanNet)"
        )
    for sub in (COLOR_DIR, DEPTH_DIR, POSE_DIR, INTRINSIC_COLOR.parent.name, *(z.folder for z in zips)):
        (folder / sub).mkdir(parents=True)
    (folder / INTRINSIC_COLOR).write_text(_matrix_text(header.intrinsic_color))
    (folder / INTRINSIC_COLOR.parent / "intrinsic_depth.txt").write_text(_matrix_text(header.intrinsic_depth))
    written = invalid = 0
    for frame in reader.frames(every):
        name = str(frame.index)
        _check_jpeg(frame.color, reader, frame.index)
        (folder / COLOR_DIR / f"{name}.jpg").write_bytes(frame.color)
        Image.fromarray(_depth_millimetres(reader, frame)).save(folder / DEPTH_DIR / f"{name}.png")
        for image_zip, by_frame in entries:
            (folder / image_zip.folder / f"{name}.png").write_bytes(image_zip.png(by_frame[frame.index]))
        (folder / POSE_DIR / f"{name}.txt").write_text(_matrix_text(frame.camera_to_world))
        written += 1
        invalid += int(not np.isfinite(frame.camera_to_world).all())
    return written, invalid


def prepare_scan(
    scan_dir: str | Path, out_root: str | Path, *, frame_skip: int = 1, overwrite: bool = False
) -> PrepareResult:
    """Convert one ScanNet scan folder into ``<out_root>/<scan name>/``.

    Args:
        scan_dir: the downloaded scan folder ``.../sceneXXXX_YY`` with ``sceneXXXX_YY.sens`` and
            ``sceneXXXX_YY_2d-label-filt.zip``; ``sceneXXXX_YY_2d-instance-filt.zip`` beside them (optional) also
            writes ``instance-filt/``.
        out_root: the dataset root to write the scene folder into.
        frame_skip: keep frames ``0, N, 2N, ...`` (names keep the stream index, like ScanNet's exporter).
        overwrite: replace an existing scene folder (the old one is removed only after the new one is complete).

    Raises:
        DataError: a missing or malformed input (one line naming the file), or the destination exists.
    """
    scan_dir = Path(scan_dir).expanduser().resolve()
    out_root = Path(out_root).expanduser().resolve()
    if frame_skip < 1:
        raise ConfigError(f"--frame-skip {frame_skip}; expected 1 or more")
    scene = scan_dir.name
    if not scan_dir.is_dir():
        raise DataError(f"{scan_dir}: expected a ScanNet scan folder holding {scene}.sens, found nothing")
    if not SCENE_NAME.match(scene):
        raise DataError(f"{scan_dir}: folder name {scene!r}; expected a ScanNet scan folder named sceneXXXX_YY")
    sens_path = scan_dir / f"{scene}.sens"
    zip_path = scan_dir / f"{scene}_2d-{LABEL_DIR}.zip"
    instance_zip = scan_dir / f"{scene}_2d-{INSTANCE_DIR}.zip"
    if not sens_path.is_file():
        raise DataError(f"{sens_path}: missing; expected the scan's RGB-D stream from the ScanNet release")
    if not zip_path.is_file():
        raise DataError(f"{zip_path}: missing; expected the scan's filtered 2D labels from the ScanNet release")
    destination = out_root / scene
    if destination == scan_dir:
        raise DataError(f"{destination}: is the scan folder itself; expected --out to name a different dataset root")
    if destination.exists() and not overwrite:
        raise DataError(f"{destination}: already exists; expected a new folder (pass --overwrite to replace it)")
    out_root.mkdir(parents=True, exist_ok=True)
    temporary = Path(tempfile.mkdtemp(prefix=f".{scene}.partial-", dir=out_root))
    try:
        with ExitStack() as stack:
            zips = [_open_zip(stack, zip_path, LABEL_DIR)]
            if instance_zip.is_file():
                zips.append(_open_zip(stack, instance_zip, INSTANCE_DIR))
            reader = stack.enter_context(SensReader(sens_path))
            try:
                written, invalid = _write_scene(temporary, reader, zips, frame_skip)
            except OSError as exc:
                raise DataError(f"{temporary}: writing failed ({exc})") from None
            total = reader.header.num_frames
        _make_shareable(temporary)
        if destination.exists():
            retired = Path(tempfile.mkdtemp(prefix=f".{scene}.old-", dir=out_root))
            destination.rename(retired / scene)
            temporary.rename(destination)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            temporary.rename(destination)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    return PrepareResult(scene, destination, written, total, invalid, instances=len(zips) > 1)


def _make_shareable(folder: Path) -> None:
    """Give the scene folder the mode a plain ``mkdir`` would (``mkdtemp`` makes it 0700, unreadable to other users of
    a shared dataset root)."""
    umask = os.umask(0)
    os.umask(umask)
    folder.chmod(0o777 & ~umask)



def main(argv: list[str]) -> int:
    """Entry point of ``data prepare-scannet``; prints how many frames were written and where."""
    parser = ArgumentParser(
        prog="gpnerf_core data prepare-scannet",
        description="Turn a ScanNet scan (.sens + _2d-label-filt.zip, optionally _2d-instance-filt.zip) into the "
        "layout the scannet dataset reads.",
    )
    parser.add_argument("scan", type=Path, help="the scan folder sceneXXXX_YY holding sceneXXXX_YY.sens")
    parser.add_argument("--out", type=Path, default=Path(DEFAULT_OUT), help=f"dataset root (default {DEFAULT_OUT})")
    parser.add_argument("--frame-skip", type=int, default=1, help="keep every N-th frame (default 1: all)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    args = parser.parse_args(argv)
    result = prepare_scan(args.scan, args.out, frame_skip=args.frame_skip, overwrite=args.overwrite)
    print(
        f"wrote {result.frames} of {result.total_frames} frames of {result.scene} to {result.folder} "
        f"(frame skip {args.frame_skip}; {result.invalid_poses} with an invalid pose, which the loader drops)"
    )
    if result.instances:
        print(f"instance ids: {INSTANCE_DIR}/ from {result.scene}_2d-{INSTANCE_DIR}.zip")
    tsv = result.folder.parent / LABEL_MAP_NAME
    if not tsv.is_file():
        print(f"note: the scannet dataset also needs {tsv} ({LABEL_MAP_SOURCE})")
    return 0
