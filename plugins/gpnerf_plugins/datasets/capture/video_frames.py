"""Frames for structure from motion: decoded from a video (imageio's ffmpeg plugin, imageio-ffmpeg's own binary) or read
from an image folder, picked evenly (``frames``) or every n-th (``every``), downscaled (``max_size``), and cleared of
blurry ones by ``SHARPNESS_RULE``.

A folder's images are taken in natural name order (``img_2`` before ``img_10``) and must all have one size (one
camera). Frames are written as ``frame_00001.png``, ``frame_00002.png``, ... in that order, so COLMAP's sequential
matcher (which orders images by name) sees them in capture order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from gpnerf_core import ConfigError, DataError
from gpnerf_plugins.datasets.capture.colmap_import import IMAGE_SUFFIXES, natural_key
from gpnerf_plugins.datasets.common.image_io import decode_image, image_size, one_line_error

MIN_FRAMES = 8
"""Fewest frames (after dropping blurry ones) handed to structure from motion."""
DEFAULT_VIDEO_FRAMES = 100
"""Frames picked from a video when neither ``frames`` nor ``every`` is given (a folder keeps all its images)."""
SHARPNESS_WINDOW = 9
DEFAULT_SHARPNESS = 0.5
SHARPNESS_RULE = (
    "sharpness = variance of the Laplacian of the grey frame (after --max-size); a frame is dropped when its "
    f"sharpness is below FRACTION x the median sharpness of the {SHARPNESS_WINDOW} picked frames centred on it "
    f"(itself included); FRACTION is --sharpness (default {DEFAULT_SHARPNESS:g}; 0 keeps every frame)"
)
FRAME_NAME = "frame_{:05d}.png"


@dataclass(frozen=True)
class SourceFrame:
    """One picked frame: ``source`` is the video's frame index or the folder's file name; ``rgb`` uint8 [H, W, 3]."""

    source: int | str
    rgb: np.ndarray


@dataclass
class FrameSet:
    """Frames picked from one video or folder.

    Attributes:
        kind: ``"video"`` or ``"folder"``.
        total: frames in the video, images in the folder.
        source_size: ``(width, height)`` of the source frames, pixels.
        frames: the picked frames (downscaled), in capture order; blurry ones removed by ``drop_blurry``.
        blurry: the frames ``drop_blurry`` removed: ``{"source", "sharpness", "neighbour_median"}``.
    """

    kind: str
    total: int
    source_size: tuple[int, int]
    frames: list[SourceFrame]
    blurry: list[dict[str, object]] = field(default_factory=list)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the picked frames."""
        height, width = self.frames[0].rgb.shape[:2]
        return width, height


def pick(total: int, frames: int | None, every: int | None) -> list[int]:
    """Indices of the frames to keep out of ``total``: every ``every``-th from 0, or ``frames`` evenly spaced
    (first and last included; all when ``frames >= total``), or all."""
    if every is not None:
        return list(range(0, total, every))
    if frames is None or frames >= total:
        return list(range(total))
    return sorted({int(i) for i in np.rint(np.linspace(0, total - 1, frames))})


def target_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """``(width, height)`` scaled down so the longer side is at most ``max_size`` (0: unchanged)."""
    if max_size <= 0 or max(width, height) <= max_size:
        return width, height
    scale = max_size / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def resize(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """uint8 RGB resized to ``(width, height)`` with PIL's antialiased Lanczos filter (unchanged if already so)."""
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS))


def read_video(
    path: Path, frames: int | None, every: int | None, max_size: int, progress: bool | None = None
) -> FrameSet:
    """Decode ``path`` once, keeping the picked frames (``pick``), each downscaled to ``max_size``.

    Raises:
        DataError: ffmpeg cannot open or decode the file, or it holds no frame.
    """
    import imageio.v2 as imageio

    expected = "expected a video file ffmpeg decodes (MP4, MOV, MKV, AVI, ...)"
    kept: list[SourceFrame] = []
    try:
        reader = imageio.get_reader(path, "ffmpeg")
        try:
            total = reader.count_frames()
            if total < 1:
                raise DataError(f"{path}: holds no video frame; {expected}")
            wanted = set(pick(total, frames, every))
            source_size = None
            disable = None if progress is None else not progress
            for index, rgb in enumerate(tqdm(reader, total=total, desc="frames", unit="frame", disable=disable)):
                if source_size is None:
                    source_size = (int(rgb.shape[1]), int(rgb.shape[0]))
                if index in wanted:
                    rgb = np.ascontiguousarray(rgb[..., :3], dtype=np.uint8)
                    kept.append(SourceFrame(index, resize(rgb, target_size(*source_size, max_size))))
        finally:
            reader.close()
    except DataError:
        raise
    except Exception as exc:  # imageio/ffmpeg raise OSError, RuntimeError, IndexError, ... on a bad stream
        raise DataError(f"{path}: cannot decode as a video ({one_line_error(exc)}); {expected}") from None
    if not kept:
        raise DataError(f"{path}: no frame could be decoded; {expected}")
    return FrameSet("video", total, source_size, kept)


def folder_images(path: Path) -> list[Path]:
    """The image files directly in ``path``, in natural name order."""
    files = [p for p in path.iterdir()
             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_folder(
    path: Path, frames: int | None, every: int | None, max_size: int, progress: bool | None = None
) -> FrameSet:
    """The picked images of a folder, each downscaled to ``max_size``.

    Raises:
        DataError: no image file, an unreadable image, or images of different sizes (named with both sizes).
    """
    files = folder_images(path)
    if not files:
        raise DataError(f"{path}: no image file ({', '.join(IMAGE_SUFFIXES)}); expected a folder of photos or frames")
    sizes = [image_size(f, "an image file") for f in files]
    for file, (height, width) in zip(files, sizes):
        if (height, width) != sizes[0]:
            raise DataError(
                f"{file}: {width}x{height} pixels, but {files[0].name} is {sizes[0][1]}x{sizes[0][0]}; expected every "
                "image of the folder the same size (one camera)"
            )
    source_size = (sizes[0][1], sizes[0][0])
    size = target_size(*source_size, max_size)
    kept = []
    disable = None if progress is None else not progress
    for index in tqdm(pick(len(files), frames, every), desc="frames", unit="frame", disable=disable):
        rgb = np.asarray(decode_image(files[index], "an image file").convert("RGB"))
        kept.append(SourceFrame(files[index].name, resize(rgb, size)))
    return FrameSet("folder", len(files), source_size, kept)


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (ITU-R 601 luma, 0-255): high for sharp edges, low when blurred."""
    grey = np.asarray(rgb, dtype=np.float64)[..., :3] @ np.array([0.299, 0.587, 0.114])
    from scipy import ndimage  # here: scipy.ndimage costs every command 0.3 s at start

    return float(ndimage.laplace(grey).var())


def blurry(scores: np.ndarray, fraction: float, window: int = SHARPNESS_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """``(mask, medians)``: which frames ``SHARPNESS_RULE`` drops, and each frame's neighbourhood median."""
    scores = np.asarray(scores, dtype=np.float64)
    half = window // 2
    medians = np.array([np.median(scores[max(0, i - half): i + half + 1]) for i in range(scores.size)])
    return scores < fraction * medians, medians


def drop_blurry(frame_set: FrameSet, fraction: float) -> FrameSet:
    """Remove the blurry frames (``SHARPNESS_RULE``) in place, recording them in ``frame_set.blurry``."""
    if fraction <= 0 or not frame_set.frames:
        return frame_set
    scores = np.array([sharpness(f.rgb) for f in frame_set.frames])
    mask, medians = blurry(scores, fraction)
    frame_set.blurry = [
        {"source": f.source, "sharpness": round(float(s), 3), "neighbour_median": round(float(m), 3)}
        for f, s, m, drop in zip(frame_set.frames, scores, medians, mask) if drop
    ]
    frame_set.frames = [f for f, drop in zip(frame_set.frames, mask) if not drop]
    return frame_set


def load_frames(source: Path, *, frames: int | None = None, every: int | None = None, max_size: int = 0,
                sharpness_fraction: float = DEFAULT_SHARPNESS, progress: bool | None = None) -> FrameSet:
    """Pick, downscale and de-blur the frames of a video file or an image folder.

    Raises:
        ConfigError: ``frames`` and ``every`` both given, or one below 1.
        DataError: ``source`` missing, undecodable, a folder of mixed sizes, or fewer than ``MIN_FRAMES`` frames left.
    """
    if frames is not None and every is not None:
        raise ConfigError(f"--frames {frames} and --every {every}; expected one of them")
    for option, value in (("--frames", frames), ("--every", every)):
        if value is not None and value < 1:
            raise ConfigError(f"{option} {value}; expected 1 or more")
    if source.is_dir():
        frame_set = read_folder(source, frames, every, max_size, progress)
    elif source.is_file():
        frame_set = read_video(source, frames if frames or every else DEFAULT_VIDEO_FRAMES, every, max_size, progress)
    else:
        raise DataError(f"{source}: not found; expected a video file or a folder of images")
    picked = len(frame_set.frames)
    drop_blurry(frame_set, sharpness_fraction)
    if len(frame_set.frames) < MIN_FRAMES:
        raise DataError(
            f"{source}: {len(frame_set.frames)} frames ({picked} picked of {frame_set.total}, "
            f"{len(frame_set.blurry)} blurry); expected at least {MIN_FRAMES} (a longer video, a larger --frames or a "
            "smaller --every; --sharpness 0 keeps blurry frames)"
        )
    return frame_set


def write_frames(frame_set: FrameSet, folder: Path) -> dict[str, int | str]:
    """Write the frames as ``frame_00001.png``, ... into ``folder``; returns ``{file name: source}``."""
    folder.mkdir(parents=True, exist_ok=True)
    names = {}
    for number, frame in enumerate(frame_set.frames, start=1):
        name = FRAME_NAME.format(number)
        Image.fromarray(frame.rgb).save(folder / name, format="PNG")
        names[name] = frame.source
    return names
