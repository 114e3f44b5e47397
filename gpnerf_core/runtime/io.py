"""Atomic file writing: a reader sees either the old file or the complete new one, never a partial file.

Every writer goes to a hidden temporary file in the destination's folder, flushes and fsyncs it, then
``os.replace``s it over the destination. On any error the temporary file is deleted and the destination
is left as it was (absent if it did not exist). Parent folders are created as needed.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import struct
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from gpnerf_core.errors import ConfigError, NonFiniteError

__all__ = [
    "check_output_folder",
    "atomic_open",
    "atomic_save_png",
    "atomic_torch_save",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "encode_png",
]


def _current_umask() -> int:
    # os.umask can only be read by setting it; done once, at import, before any threads write files.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_current_umask()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb", encoding: str | None = None) -> Iterator[IO[Any]]:
    """Open a temporary file that replaces ``path`` when the ``with`` block ends without an error.

    Args:
        path: destination file; its parent folders are created.
        mode: ``"wb"`` or ``"w"``.
        encoding: text encoding for mode ``"w"`` (default utf-8).

    Yields:
        The open temporary file object.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open mode must be 'wb' or 'w', got {mode!r}")
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        if exc.errno in DISK_FULL:
            raise writing_error(exc, target) from None
        raise
    try:
        text_encoding = (encoding or "utf-8") if mode == "w" else None
        with os.fdopen(fd, mode, encoding=text_encoding) as handle:
            # mkstemp creates the file 0600; give the final file the permissions a plain open() would.
            os.chmod(tmp_name, _FILE_MODE)
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        if exc.filename is None or exc.errno in DISK_FULL:  # a write, flush or fsync of the temporary file
            raise writing_error(exc, target) from None
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    _fsync_dir(target.parent)


DISK_FULL = frozenset(code for code in (errno.ENOSPC, getattr(errno, "EDQUOT", None)) if code is not None)
"""The errors of a write that found no space (a full disk, a used-up quota)."""


def writing_error(exc: OSError, target: Path) -> OSError:
    """``exc``, raised while ``target`` was written (through its temporary file, which is gone), as an ``OSError``
    naming ``target``, and on a full disk saying so: the command line prints it as one line, ``<file>: <why>``."""
    if exc.errno in DISK_FULL:
        why = f"{exc.strerror or 'No space left on device'} while writing it: the disk is full (nothing half-written left)"
    else:
        why = f"{exc.strerror or exc} while writing it (nothing half-written left)"
    return OSError(exc.errno, why, str(target))


def _fsync_dir(folder: Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened."""
    try:
        dir_fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "wb") as handle:
        handle.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (no newline translation); returns the path."""
    return atomic_write_bytes(path, text.encode(encoding))


def _find_non_finite(obj: Any, where: str = "$") -> str | None:
    """Return the JSON path of the first NaN/Inf float inside ``obj``, or None."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else where
    if isinstance(obj, dict):
        for key, value in obj.items():
            found = _find_non_finite(value, f"{where}.{key}")
            if found is not None:
                return found
    elif isinstance(obj, (list, tuple)):
        for index, value in enumerate(obj):
            found = _find_non_finite(value, f"{where}[{index}]")
            if found is not None:
                return found
    return None


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as JSON (sorted keys, indent 2, trailing newline) atomically; returns the path.

    Raises:
        NonFiniteError: a NaN or infinite float is inside ``obj`` (JSON has no such values).
        TypeError: ``obj`` holds a value JSON cannot represent (e.g. a tensor).
    """
    bad = _find_non_finite(obj)
    if bad is not None:
        raise NonFiniteError(f"{path}: refusing to write a non-finite number at {bad}; JSON allows finite floats only")
    text = json.dumps(obj, sort_keys=True, indent=2, allow_nan=False) + "\n"
    return atomic_write_text(path, text)


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def encode_png(array: np.ndarray) -> bytes:
    """Encode an image as PNG bytes, bit-exactly.

    Args:
        array: ``[H, W]`` (grey) or ``[H, W, 3]`` (RGB), dtype uint8 or uint16.

    Returns:
        The PNG file content (8 or 16 bits per channel, no filtering, zlib level 6).
    """
    array = np.asarray(array)
    if array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG image dtype must be uint8 or uint16, got {array.dtype}")
    if array.ndim == 2:
        colour_type = 0
    elif array.ndim == 3 and array.shape[2] == 3:
        colour_type = 2
    else:
        raise ValueError(f"PNG image shape must be [H, W] or [H, W, 3], got {list(array.shape)}")
    height, width = int(array.shape[0]), int(array.shape[1])
    if height == 0 or width == 0:
        raise ValueError(f"PNG image must not be empty, got shape {list(array.shape)}")
    bit_depth = 8 if array.dtype == np.uint8 else 16
    rows = np.ascontiguousarray(array, dtype=">u2" if bit_depth == 16 else np.uint8).reshape(height, -1)
    # Each scanline is prefixed with filter type 0 (none).
    raw = np.concatenate([np.zeros((height, 1), np.uint8), rows.view(np.uint8)], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", header)
        + _png_chunk(b"IDAT", zlib.compress(raw, 6))
        + _png_chunk(b"IEND", b"")
    )


def atomic_save_png(path: str | os.PathLike[str], array: np.ndarray) -> Path:
    """Save a uint8/uint16 ``[H, W]`` or ``[H, W, 3]`` array as a PNG atomically; returns the path."""
    return atomic_write_bytes(path, encode_png(array))


def atomic_torch_save(path: str | os.PathLike[str], obj: Any) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (a checkpoint is never left half-written); returns the path."""
    with atomic_open(path, "wb") as handle:
        writer = _WriteErrors(handle)
        try:
            torch.save(obj, writer)
        except (RuntimeError, OSError):
            error = writer.error  # a full disk: torch re-raises it bare, or as a RuntimeError about stream positions
            if error is None:
                raise
            raise writing_error(error, Path(path)) from None
    return Path(path)


class _WriteErrors:
    """A binary file that remembers the ``OSError`` its ``write`` raised (ENOSPC, EIO), which ``torch.save`` would
    otherwise report as a RuntimeError about stream positions."""

    def __init__(self, handle: IO[bytes]) -> None:
        self.handle = handle
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        try:
            return self.handle.write(data)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.handle.flush()


def check_output_folder(path: str | os.PathLike[str], option: str) -> None:
    """Refuse, before any work, an output folder that cannot be made or written: one line naming ``option`` and why.

    Nothing is created: the nearest existing ancestor must be a writable folder (or ``path`` itself one).
    """
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise ConfigError(f"{option} {target}: expected a folder, found a file")
    ancestor = target
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{option} {target}: {ancestor} is a file, so no folder can be made under it")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {target}: {ancestor} is not writable")
