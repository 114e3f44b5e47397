"""Atomic writers: content, folders, permissions, and nothing left behind on failure."""

from __future__ import annotations

import json
import contextlib
import os
import struct
import zlib

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.runtime import io as gio
from gpnerf_core.errors import NonFiniteError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_write_bytes_creates_parents_and_leaves_only_the_file(tmp_path):
    target = tmp_path / "a" / "b" / "blob.bin"
    assert gio.atomic_write_bytes(target, b"\x00\x01xyz") == target
    assert target.read_bytes() == b"\x00\x01xyz"
    assert os.listdir(target.parent) == ["blob.bin"]
    assert os.stat(target).st_mode & 0o777 == 0o666 & ~_umask()


def test_write_text_replaces_existing_file(tmp_path):
    target = tmp_path / "note.txt"
    target.write_text("old")
    gio.atomic_write_text(target, "new\nline ü")
    assert target.read_text(encoding="utf-8") == "new\nline ü"
    assert os.listdir(tmp_path) == ["note.txt"]


def test_write_json_sorted_indented_round_trip(tmp_path):
    target = tmp_path / "metrics.json"
    obj = {"b": 1, "a": {"z": [1.5, None], "y": "s"}}
    gio.atomic_write_json(target, obj)
    text = target.read_text()
    assert text == json.dumps(obj, sort_keys=True, indent=2) + "\n"
    assert text.index('"a"') < text.index('"b"')
    assert json.loads(text) == obj


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_write_json_refuses_non_finite_and_names_the_key(tmp_path, bad):
    target = tmp_path / "metrics.json"
    with pytest.raises(NonFiniteError, match=r"\$\.scores\[1\]"):
        gio.atomic_write_json(target, {"ok": 1.0, "scores": [0.5, bad]})
    assert os.listdir(tmp_path) == []


def test_failure_mid_write_leaves_nothing(tmp_path):
    target = tmp_path / "sub" / "partial.bin"
    with pytest.raises(RuntimeError, match="disk on fire"):
        with gio.atomic_open(target, "wb") as handle:
            handle.write(b"x" * 10_000)
            handle.flush()
            raise RuntimeError("disk on fire")
    assert not target.exists()
    assert os.listdir(target.parent) == []


def test_failure_mid_write_keeps_the_previous_file(tmp_path):
    target = tmp_path / "metrics.json"
    gio.atomic_write_json(target, {"v": 1})
    with pytest.raises(TypeError):
        gio.atomic_write_json(target, {"v": object()})
    with pytest.raises(RuntimeError):
        with gio.atomic_open(target, "w") as handle:
            handle.write("{garbage")
            raise RuntimeError("interrupted")
    assert json.loads(target.read_text()) == {"v": 1}
    assert os.listdir(tmp_path) == ["metrics.json"]


def test_failed_fsync_or_replace_cleans_up(tmp_path, monkeypatch):
    target = tmp_path / "x.bin"

    def boom(*_args):
        raise OSError("simulated I/O error")

    monkeypatch.setattr(gio.os, "fsync", boom)
    with pytest.raises(OSError, match="simulated"):
        gio.atomic_write_bytes(target, b"data")
    assert os.listdir(tmp_path) == []
    monkeypatch.undo()
    monkeypatch.setattr(gio.os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        gio.atomic_write_bytes(target, b"data")
    assert os.listdir(tmp_path) == []


def test_torch_save_round_trip_and_unpicklable_object(tmp_path):
    target = tmp_path / "ckpt" / "model.pt"
    state = {"w": torch.arange(6.0).reshape(2, 3), "step": 7}
    gio.atomic_torch_save(target, state)
    loaded = torch.load(target, weights_only=True)
    assert loaded["step"] == 7 and torch.equal(loaded["w"], state["w"])
    bad = tmp_path / "ckpt" / "bad.pt"
    with pytest.raises(Exception):
        gio.atomic_torch_save(bad, {"w": torch.zeros(3), "f": lambda: 0})
    assert os.listdir(target.parent) == ["model.pt"]


def test_a_full_disk_during_torch_save_is_an_oserror_naming_the_file(tmp_path, monkeypatch):
    """torch's zip writer reports a failed write as a RuntimeError about stream positions; the OSError is kept."""
    import errno

    real_open = gio.atomic_open

    class FullDisk:
        def __init__(self, handle):
            self.handle = handle

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self):
            self.handle.flush()

    @contextlib.contextmanager
    def full_disk_open(path, mode="wb", encoding=None):
        with real_open(path, mode, encoding) as handle:
            yield FullDisk(handle)

    monkeypatch.setattr(gio, "atomic_open", full_disk_open)
    target = tmp_path / "step_0000001.pt"
    with pytest.raises(OSError) as error:
        gio.atomic_torch_save(target, {"w": torch.zeros(100_000)})
    assert error.value.errno == errno.ENOSPC and error.value.filename == str(target)
    assert os.listdir(tmp_path) == []


def _decode_png(data: bytes) -> tuple[tuple[int, ...], np.ndarray]:
    """Independent minimal decoder for unfiltered PNGs (what encode_png writes)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, payload = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + payload)
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", payload)
        elif kind == b"IDAT":
            idat += payload
        pos += 12 + length
    width, height, depth, colour = header[:4]
    channels = 3 if colour == 2 else 1
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(height, -1)
    assert (raw[:, 0] == 0).all()
    pixels = raw[:, 1:].copy().view(">u2" if depth == 16 else np.uint8).reshape(height, width, channels)
    return header, pixels.squeeze(-1) if channels == 1 else pixels


@pytest.mark.parametrize(
    ("shape", "dtype"), [((5, 7), np.uint8), ((5, 7, 3), np.uint8), ((4, 6), np.uint16), ((4, 6, 3), np.uint16)]
)
def test_png_is_bit_exact(tmp_path, shape, dtype):
    rng = np.random.default_rng(0)
    array = rng.integers(0, np.iinfo(dtype).max + 1, size=shape, dtype=dtype)
    target = tmp_path / "img.png"
    gio.atomic_save_png(target, array)
    header, decoded = _decode_png(target.read_bytes())
    assert header[:4] == (shape[1], shape[0], 8 * np.dtype(dtype).itemsize, 2 if len(shape) == 3 else 0)
    assert np.array_equal(decoded.astype(dtype), array)
    if not (dtype == np.uint16 and len(shape) == 3):  # Pillow cannot hold 16-bit RGB
        assert np.array_equal(np.asarray(Image.open(target)), array)
    assert os.listdir(tmp_path) == ["img.png"]


@pytest.mark.parametrize(
    "array", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 4), np.uint8), np.zeros((0, 3), np.uint8)]
)
def test_png_rejects_bad_arrays(tmp_path, array):
    with pytest.raises(ValueError):
        gio.atomic_save_png(tmp_path / "bad.png", array)
    assert os.listdir(tmp_path) == []


def test_atomic_open_rejects_read_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"):
        with gio.atomic_open(tmp_path / "f", "r"):
            pass


@pytest.mark.parametrize("writer", ["bytes", "text", "json", "ply"])
def test_a_full_disk_names_the_file_being_written_and_leaves_nothing(tmp_path, monkeypatch, writer):
    """Issue 55: ``export`` onto a full disk said "No space left on device" without the file (the write of the
    temporary file raised an OSError that names none)."""
    import errno

    from gpnerf_core.runtime.ply import write_ply

    real_fdopen = os.fdopen

    class FullDisk:
        def __init__(self, handle):
            self.handle = handle

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

        def write(self, data):
            self.handle.write(data[:10])
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.handle, name)

    monkeypatch.setattr(gio.os, "fdopen", lambda *args, **kwargs: FullDisk(real_fdopen(*args, **kwargs)))
    target = tmp_path / "export" / "gaussians.ply"
    write = {"bytes": lambda: gio.atomic_write_bytes(target, b"x" * 100),
             "text": lambda: gio.atomic_write_text(target, "x" * 100),
             "json": lambda: gio.atomic_write_json(target, {"x": 1}),
             "ply": lambda: write_ply(target, {"x": np.zeros(4, np.float32)})}[writer]
    with pytest.raises(OSError) as error:
        write()
    assert error.value.errno == errno.ENOSPC and error.value.filename == str(target)
    assert error.value.strerror.startswith("No space left on device while writing it: the disk is full")
    assert os.listdir(target.parent) == []  # no temporary file, no partial file
