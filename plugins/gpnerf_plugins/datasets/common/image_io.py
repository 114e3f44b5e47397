"""Image decoding and resizing shared by the dataset readers and layout checkers.

A file that cannot be opened or decoded is an ``ImageError``: a one-line ``DataError`` naming the file, never a
PIL or scikit-image traceback. Resizes are area-aligned (destination pixel centre ``u + 0.5`` samples the source at
``(u + 0.5) * src / dst``), matching pixel centres at integers (``gpnerf_core.types``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from gpnerf_core import DataError


def one_line_error(exc: BaseException) -> str:
    """``Type: first line of the message`` (some decoders raise multi-line messages)."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


class ImageError(DataError):
    """``<path>: unreadable image (<reason>); expected <expected>``.

    Attributes:
        path: the file.
        reason: the decoder's error on one line (``one_line_error``).
        missing: the file does not exist (readers that word that case differently test this).
    """

    def __init__(self, path: Path, exc: BaseException, expected: str) -> None:
        self.path, self.reason, self.missing = Path(path), one_line_error(exc), isinstance(exc, FileNotFoundError)
        super().__init__(f"{path}: unreadable image ({self.reason}); expected {expected}")


def image_header(path: Path, expected: str = "a PNG") -> tuple[tuple[int, int], str]:
    """``((H, W), PIL mode)`` from the image header, without decoding the pixels."""
    try:
        with Image.open(path) as image:
            (width, height), mode = image.size, image.mode
    except Exception as exc:
        raise ImageError(path, exc, expected) from None
    return (height, width), mode


def image_size(path: Path, expected: str = "a PNG") -> tuple[int, int]:
    """``(H, W)`` from the image header, without decoding the pixels."""
    return image_header(path, expected)[0]


def decode_image(path: Path, expected: str = "an image") -> Image.Image:
    """Fully decode an image with PIL (a truncated or corrupt file raises ``ImageError``)."""
    try:
        with Image.open(path) as image:
            image.load()
            return image.copy()
    except Exception as exc:
        raise ImageError(path, exc, expected) from None


def read_png(path: Path) -> np.ndarray:
    """Decode a PNG to an array with its stored dtype (uint8 or uint16) and channels."""
    from skimage import io as skio  # here: skimage.io and .transform cost every command 0.6 s at start

    try:
        return np.asarray(skio.imread(path))
    except Exception as exc:
        raise ImageError(path, exc, "a PNG") from None


def describe(image: np.ndarray) -> str:
    """What a format check found: ``<dtype> image of shape <shape>``."""
    return f"{image.dtype} image of shape {image.shape}"


def is_rgb8(image: np.ndarray) -> bool:
    """``[H, W, 3]`` or ``[H, W, 4]`` uint8."""
    return image.ndim == 3 and image.shape[2] in (3, 4) and image.dtype == np.uint8


def is_integer_map(image: np.ndarray) -> bool:
    """``[H, W]`` of an integer dtype (depth in millimetres, class or instance ids)."""
    return image.ndim == 2 and np.issubdtype(image.dtype, np.integer)


def read_rgb_png(path: Path) -> np.ndarray:
    """An 8-bit RGB(A) PNG as float32 ``[H, W, 3]`` in [0, 1] (alpha dropped)."""
    image = read_png(path)
    if not is_rgb8(image):
        raise DataError(f"{path}: {describe(image)}; expected 8-bit RGB or RGBA")
    return image[..., :3].astype(np.float32) / 255.0


EIGHT_BIT_DEPTH = "an 8-bit PNG (at most 255 units: 0.255 m in millimetres); expected a 16-bit depth PNG"
"""Why an 8-bit depth PNG is refused: its values cannot hold depth in the units depth PNGs use."""


EIGHT_BIT_MODES = ("1", "L", "P")
"""PIL modes of a single-channel PNG of at most 8 bits."""


def check_depth_mode(path: Path, mode: str) -> None:
    """Refuse a depth PNG whose header (PIL ``mode``) says 8 bits, before any pixel is decoded (other wrong formats,
    several channels, are refused when the frame decodes).

    Raises:
        DataError: naming ``path``, what it is and what is expected.
    """
    if mode in EIGHT_BIT_MODES:
        raise DataError(f"{path}: {EIGHT_BIT_DEPTH}")


def read_integer_png(path: Path, what: str, *, depth: bool = False) -> np.ndarray:
    """A single-channel integer PNG of ``what`` (named in the error) as int64 ``[H, W]``; ``depth``: refuse 8 bits."""
    image = read_png(path)
    if not is_integer_map(image):
        raise DataError(f"{path}: {describe(image)}; expected a single-channel integer PNG of {what}")
    if depth and image.dtype == np.uint8:
        raise DataError(f"{path}: {EIGHT_BIT_DEPTH}")
    return image.astype(np.int64)


def nearest_indices(src: int, dst: int) -> np.ndarray:
    """``[dst]`` int64: source index of each destination pixel centre for a nearest-neighbour resize."""
    return np.minimum(((np.arange(dst) + 0.5) * src / dst).astype(np.int64), src - 1)


def resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``[h, w, ...]`` -> ``[height, width, ...]`` by nearest neighbour (depth, labels); the input if already that size."""
    if image.shape[:2] == (height, width):
        return image
    rows = nearest_indices(image.shape[0], height)
    cols = nearest_indices(image.shape[1], width)
    return image[rows[:, None], cols[None, :]]


def resize_rgb(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """Antialiased bilinear resize of float32 ``[H, W, 3]`` RGB in [0, 1]; the input if already that size."""
    if rgb.shape[:2] == (height, width):
        return rgb
    from skimage.transform import resize as sk_resize

    out = sk_resize(rgb, (height, width), order=1, anti_aliasing=True, preserve_range=True)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
