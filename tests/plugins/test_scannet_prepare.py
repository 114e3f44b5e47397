"""`.sens` reading and `data prepare-scannet`, on tiny scans written here byte by byte from ScanNet's format.

The writer below follows ScanNet's sensorData.h (writeHeaderToFile, RGBDFrame::saveToFile) independently of the
reader under test: little-endian, version 4, name, 4 row-major float32 4x4 matrices, compression types,
sizes, depth shift, frame count, then per frame pose, 2 timestamps, 2 byte counts, colour and depth bytes.
"""

from __future__ import annotations

import io
import os
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.scannet.dataset import ScanNetScenes
from gpnerf_plugins.datasets.scannet.prepare import main, prepare_scan
from gpnerf_plugins.datasets.scannet.sens import SensReader

SCENE = "scene0042_00"
COLOR_HW, DEPTH_HW = (48, 64), (24, 32)
K_COLOR = np.array([[50.0, 0, 31.5, 0], [0, 52.0, 23.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float32)
K_DEPTH = np.array([[25.0, 0, 15.5, 0], [0, 26.0, 11.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float32)
EXTRINSIC_DEPTH = np.eye(4, dtype=np.float32)
EXTRINSIC_DEPTH[:3, 3] = (0.025, 0.0, 0.0)


def pose_of(index: int) -> np.ndarray:
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, 3] = (0.1 + 0.3 * index, -0.2 * index, 1.5)
    c2w[0, 0], c2w[0, 1], c2w[1, 0], c2w[1, 1] = 0.8, 0.6, -0.6, 0.8  # a rotation about z with distinctive values
    return c2w


def jpeg_of(index: int) -> bytes:
    rng = np.random.default_rng(index)
    buffer = io.BytesIO()
    Image.fromarray(rng.integers(0, 256, (*COLOR_HW, 3), dtype=np.uint8)).save(buffer, format="JPEG", quality=90)
    return buffer.getvalue()


def depth_of(index: int) -> np.ndarray:
    return (500 + 250 * index + np.arange(DEPTH_HW[0] * DEPTH_HW[1]).reshape(DEPTH_HW)).astype(np.uint16)


def labels_of(index: int) -> np.ndarray:
    """Raw ids: left half 1 (wall), right half 3 (-> otherfurniture), top rows 0 and one block of unknown 999."""
    labels = np.ones(COLOR_HW, dtype=np.uint16)
    labels[:, COLOR_HW[1] // 2 :] = 3
    labels[: 2 + index] = 0
    labels[-4:, :4] = 999
    return labels


def instances_of(index: int) -> np.ndarray:
    """8-bit instance ids at colour resolution: 0 (not annotated) on top, objects 1..4 in columns, shifted per frame."""
    ids = (np.arange(COLOR_HW[1])[None, :] // 16 + index) % 4 + 1
    ids = np.repeat(ids, COLOR_HW[0], axis=0).astype(np.uint8)
    ids[:3] = 0
    return ids


def png_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def write_sens(
    path: Path,
    num_frames: int = 3,
    *,
    invalid=(),
    version: int = 4,
    color_type: int = 2,
    depth_shift: float = 1000.0,
    depth_bytes=None,
) -> Path:
    out = bytearray(struct.pack("<I", version))
    name = b"StructureSensor"
    out += struct.pack("<Q", len(name)) + name
    for matrix in (K_COLOR, np.eye(4), K_DEPTH, EXTRINSIC_DEPTH):
        out += np.asarray(matrix, dtype="<f4").tobytes()  # row-major
    out += struct.pack("<ii", color_type, 1)
    out += struct.pack("<4I", COLOR_HW[1], COLOR_HW[0], DEPTH_HW[1], DEPTH_HW[0])
    out += struct.pack("<f", depth_shift)
    out += struct.pack("<Q", num_frames)
    for i in range(num_frames):
        color = jpeg_of(i)
        depth = depth_bytes if depth_bytes is not None else zlib.compress(depth_of(i).astype("<u2").tobytes())
        pose = np.full((4, 4), -np.inf, dtype=np.float32) if i in invalid else pose_of(i)
        out += np.asarray(pose, dtype="<f4").tobytes()
        out += struct.pack("<4Q", 1000 * i, 1000 * i + 7, len(color), len(depth))
        out += color + depth
    out += struct.pack("<Q", 0)  # no IMU frames
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(out))
    return path


def write_label_zip(path: Path, frames, folder: str = "label-filt") -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for i in frames:
            archive.writestr(f"{folder}/{i}.png", png_bytes(labels_of(i)))
    return path


def write_instance_zip(path: Path, frames, folder: str = "instance-filt", image=instances_of) -> Path:
    """ScanNet's ``_2d-instance-filt.zip``: ``instance-filt/<i>.png`` holding ``image(i)``."""
    with zipfile.ZipFile(path, "w") as archive:
        for i in frames:
            archive.writestr(f"{folder}/{i}.png", png_bytes(image(i)))
    return path


def write_scan(tmp_path: Path, num_frames: int = 3, *, instances: bool = False, **sens_options) -> Path:
    """A scan as downloaded: ``.sens`` + label zip, and the instance zip when ``instances``."""
    scan = tmp_path / "scans" / SCENE
    write_sens(scan / f"{SCENE}.sens", num_frames, **sens_options)
    write_label_zip(scan / f"{SCENE}_2d-label-filt.zip", range(num_frames))
    if instances:
        write_instance_zip(scan / f"{SCENE}_2d-instance-filt.zip", range(num_frames))
    return scan


def write_tsv(root: Path) -> None:
    (root / "scannetv2-labels.combined.tsv").write_text("id\traw_category\tnyu40id\n1\twall\t1\n3\tshelf\t39\n")


def read_matrix(path: Path) -> np.ndarray:
    return np.loadtxt(path, dtype=np.float64).reshape(4, 4)


# -------------------------------------------------------------------------------------------------- reader


def test_reader_parses_header_and_streams_frames_lazily(tmp_path):
    sens = write_sens(tmp_path / "a.sens", 5, invalid=(3,))
    with SensReader(sens) as reader:
        header = reader.header
        assert (header.version, header.sensor_name, header.num_frames) == (4, "StructureSensor", 5)
        assert np.array_equal(header.intrinsic_color, K_COLOR) and np.array_equal(header.intrinsic_depth, K_DEPTH)
        assert np.array_equal(header.extrinsic_depth, EXTRINSIC_DEPTH)
        assert np.array_equal(header.extrinsic_color, np.eye(4))
        assert (header.color_compression, header.depth_compression) == ("jpeg", "zlib_ushort")
        assert (header.color_width, header.color_height, header.depth_width, header.depth_height) == (64, 48, 32, 24)
        assert header.depth_shift == 1000.0
        frames = list(reader.frames())
        assert [f.index for f in frames] == [0, 1, 2, 3, 4]
        assert np.array_equal(frames[2].camera_to_world, pose_of(2))
        assert np.isneginf(frames[3].camera_to_world).all()
        assert (frames[2].timestamp_color, frames[2].timestamp_depth) == (2000, 2007)
        assert frames[4].color == jpeg_of(4)
        assert np.array_equal(reader.depth_image(frames[1]), depth_of(1))
        skipped = list(reader.frames(every=2))
        assert [f.index for f in skipped] == [0, 2, 4] and skipped[1].color == jpeg_of(2)


def test_truncated_stream_fails_only_when_the_damaged_frame_is_reached(tmp_path):
    sens = write_sens(tmp_path / "a.sens", 3)
    sens.write_bytes(sens.read_bytes()[:-40])  # cut inside the last frame's depth bytes
    with SensReader(sens) as reader:
        stream = reader.frames()
        assert next(stream).index == 0 and next(stream).index == 1  # streamed before the damage is seen
        with pytest.raises(DataError, match=r"a\.sens: truncated in the depth data of frame 2; expected \d+ bytes"):
            next(stream)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: struct.pack("<I", 3) + b[4:], "version 3; expected 4"),
        (lambda b: b[:30], "truncated in the colour intrinsic"),
        (lambda b: b"", "truncated in the version"),
    ],
)
def test_bad_headers_are_one_line_errors(tmp_path, damage, message):
    sens = write_sens(tmp_path / "a.sens", 1)
    sens.write_bytes(damage(sens.read_bytes()))
    with pytest.raises(DataError, match=message):
        SensReader(sens)


# ------------------------------------------------------------------------------------------------- prepare


def test_prepare_writes_the_layout_and_the_dataset_reads_it_value_by_value(tmp_path, capsys):
    scan = write_scan(tmp_path, 3, invalid=(1,))
    out = tmp_path / "data"
    assert main([str(scan), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote 3 of 3 frames of {SCENE} to {out / SCENE}" in printed and "1 with an invalid pose" in printed
    assert "scannetv2-labels.combined.tsv" in printed  # the hint: the label map is still missing
    assert "instance" not in printed  # no instance zip: optional, nothing to say
    folder = out / SCENE
    assert not (folder / "instance-filt").exists()
    assert sorted(p.name for p in out.iterdir()) == [SCENE]  # no temporary folder left behind
    umask = os.umask(0)
    os.umask(umask)
    assert folder.stat().st_mode & 0o777 == 0o777 & ~umask  # readable by others as a plain mkdir, not mkdtemp's 0700
    for i in range(3):
        assert (folder / "color" / f"{i}.jpg").read_bytes() == jpeg_of(i)  # as stored
        depth = np.asarray(Image.open(folder / "depth" / f"{i}.png"))
        assert depth.dtype == np.uint16 and np.array_equal(depth, depth_of(i))
        assert np.array_equal(np.asarray(Image.open(folder / "label-filt" / f"{i}.png")), labels_of(i))
    assert np.array_equal(read_matrix(folder / "pose" / "0.txt").astype(np.float32), pose_of(0))
    assert np.isneginf(read_matrix(folder / "pose" / "1.txt")).all()
    assert np.array_equal(read_matrix(folder / "intrinsic" / "intrinsic_color.txt").astype(np.float32), K_COLOR)
    assert np.array_equal(read_matrix(folder / "intrinsic" / "intrinsic_depth.txt").astype(np.float32), K_DEPTH)

    write_tsv(out)
    data = ScanNetScenes(root=str(out), height=24, width=32, scenes=[SCENE])
    assert data.scenes("train") == (SCENE,)
    with pytest.warns(UserWarning, match="dropped 1 of 3 frames"):
        scene = data.load_scene(SCENE)
    assert scene.num_frames == 2
    assert torch.equal(scene.c2w, torch.from_numpy(np.stack([pose_of(0), pose_of(2)])))  # float32 round trip
    k = torch.tensor([[25.0, 0.0, 15.5], [0.0, 26.0, 11.5], [0.0, 0.0, 1.0]])  # 64x48 -> 32x24: ratios 1/2
    assert torch.allclose(scene.intrinsics, k.expand(2, 3, 3))
    with pytest.warns(UserWarning, match="ids 999"):
        frame = scene.load_frame(1)  # stream frame 2
    assert torch.equal(frame.depth, torch.from_numpy(depth_of(2).astype(np.float32) / 1000.0))  # metres
    expected = np.array([255, 0, 19, 255])[np.searchsorted([0, 1, 3, 999], labels_of(2))][1::2, 1::2]
    assert torch.equal(frame.semantic, torch.from_numpy(expected))
    assert frame.instance is None


def test_instance_zip_is_copied_for_the_written_frames_and_the_dataset_reads_it(tmp_path, capsys):
    scan = write_scan(tmp_path, 5, instances=True)
    out = tmp_path / "data"
    assert main([str(scan), "--out", str(out), "--frame-skip", "2"]) == 0
    assert f"instance ids: instance-filt/ from {SCENE}_2d-instance-filt.zip" in capsys.readouterr().out
    folder = out / SCENE
    assert sorted(p.name for p in (folder / "instance-filt").iterdir()) == ["0.png", "2.png", "4.png"]  # frame skip
    with zipfile.ZipFile(scan / f"{SCENE}_2d-instance-filt.zip") as archive:
        for i in (0, 2, 4):
            stored = archive.read(f"instance-filt/{i}.png")
            assert (folder / "instance-filt" / f"{i}.png").read_bytes() == stored  # byte for byte
            assert stored == png_bytes(instances_of(i))
    write_tsv(out)
    scene = ScanNetScenes(root=str(out), height=24, width=32, scenes=[SCENE]).load_scene(SCENE)
    with pytest.warns(UserWarning, match="ids 999"):
        frame = scene.load_frame(2)  # stream frame 4
    assert frame.instance.dtype == torch.int64
    expected = instances_of(4)[1::2, 1::2].astype(np.int64)  # nearest: centres of 2x2 cells
    assert torch.equal(frame.instance, torch.from_numpy(expected))
    assert set(np.unique(expected)) == {0, 1, 2, 3, 4}


def test_frame_skip_keeps_stream_indices_as_names(tmp_path):
    scan = write_scan(tmp_path, 5)
    result = prepare_scan(scan, tmp_path / "data", frame_skip=2)
    assert (result.frames, result.total_frames) == (3, 5)
    names = sorted((result.folder / "color").iterdir(), key=lambda p: int(p.stem))
    assert [p.name for p in names] == ["0.jpg", "2.jpg", "4.jpg"]
    assert (result.folder / "color" / "4.jpg").read_bytes() == jpeg_of(4)
    assert np.array_equal(read_matrix(result.folder / "pose" / "4.txt").astype(np.float32), pose_of(4))
    assert np.array_equal(np.asarray(Image.open(result.folder / "label-filt" / "4.png")), labels_of(4))


def test_depth_in_other_units_is_converted_to_millimetres(tmp_path):
    scan = write_scan(tmp_path, 1, depth_shift=2000.0)  # stored in half millimetres
    result = prepare_scan(scan, tmp_path / "data")
    depth = np.asarray(Image.open(result.folder / "depth" / "0.png"))
    assert np.array_equal(depth, np.rint(depth_of(0) / 2.0).astype(np.uint16))


def test_existing_destination_needs_overwrite(tmp_path):
    scan = write_scan(tmp_path, 2)
    out = tmp_path / "data"
    prepare_scan(scan, out)
    (out / SCENE / "stale.txt").write_text("old")
    with pytest.raises(DataError, match="already exists"):
        prepare_scan(scan, out)
    prepare_scan(scan, out, overwrite=True)
    assert not (out / SCENE / "stale.txt").exists() and sorted(p.name for p in out.iterdir()) == [SCENE]


def _break_scan(scan: Path, what: str) -> str:
    """Damage a written scan; returns the text the error must contain."""
    sens, labels = scan / f"{SCENE}.sens", scan / f"{SCENE}_2d-label-filt.zip"
    instances = scan / f"{SCENE}_2d-instance-filt.zip"
    if what == "instances not a zip":
        instances.write_bytes(b"PK\x03\x04 truncated")
        return f"{instances}: not a readable zip archive"
    if what == "zip without instance-filt":
        write_instance_zip(instances, range(3), folder="instance")
        return f"{instances}: no instance-filt/<frame>.png inside; expected ScanNet's _2d-instance-filt.zip"
    if what == "instance count mismatch":
        write_instance_zip(instances, range(4))
        return f"{instances}: 4 instance-filt images for 3 frames in {sens}; expected one instance-filt image per frame"
    if what == "instance names":
        write_instance_zip(instances, (0, 1, 7))
        return f"{instances}: no instance-filt/2.png; expected instance-filt images for frames 0..2"
    if what == "rgb instance entry":
        write_instance_zip(instances, range(3), image=lambda i: np.zeros((*COLOR_HW, 3), dtype=np.uint8))
        return f"{instances}: instance-filt/0.png is a PNG of mode RGB; expected a single-channel integer PNG"
    if what == "missing sens":
        sens.unlink()
        return f"{sens}: missing"
    if what == "missing zip":
        labels.unlink()
        return f"{labels}: missing"
    if what == "truncated stream":
        sens.write_bytes(sens.read_bytes()[:-40])
        return f"{sens}: truncated in the depth data of frame 2"
    if what == "zip without label-filt":
        write_label_zip(labels, range(3), folder="label")
        return f"{labels}: no label-filt/<frame>.png inside"
    if what == "count mismatch":
        write_label_zip(labels, range(2))
        return f"{labels}: 2 label-filt images for 3 frames in {sens}"
    if what == "label names":
        write_label_zip(labels, (0, 1, 5))
        return f"{labels}: no label-filt/2.png"
    if what == "not a zip":
        labels.write_bytes(b"not a zip")
        return f"{labels}: not a readable zip archive"
    if what == "bad depth stream":
        write_sens(sens, 3, depth_bytes=b"garbage")
        return f"{sens}: depth of frame 0 is not a zlib stream"
    if what == "png colour":
        write_sens(sens, 3, color_type=1)
        return f"{sens}: colour compression png; expected jpeg"
    raise AssertionError(what)


@pytest.mark.parametrize(
    "what",
    [
        "missing sens", "missing zip", "truncated stream", "zip without label-filt", "count mismatch", "label names",
        "not a zip", "bad depth stream", "png colour",
        "instances not a zip", "zip without instance-filt", "instance count mismatch", "instance names",
        "rgb instance entry",
    ],
)  # fmt: skip
def test_bad_scans_fail_with_one_line_and_write_nothing(tmp_path, what):
    scan = write_scan(tmp_path, 3, instances=True)
    expected = _break_scan(scan, what)
    out = tmp_path / "data"
    with pytest.raises(DataError) as info:
        prepare_scan(scan, out)
    assert expected in str(info.value) and "\n" not in str(info.value)
    assert not out.exists() or list(out.iterdir()) == []  # nothing half-written, no temporary folder


def test_bad_arguments_are_config_errors(tmp_path):
    scan = write_scan(tmp_path, 1)
    with pytest.raises(ConfigError, match="--frame-skip 0"):
        main([str(scan), "--frame-skip", "0"])
    with pytest.raises(ConfigError, match="unrecognized arguments: --bogus"):
        main([str(scan), "--bogus"])
    with pytest.raises(DataError, match="expected a ScanNet scan folder named sceneXXXX_YY"):
        prepare_scan(tmp_path, tmp_path / "data")


def test_prepare_command_through_the_cli(tmp_path):
    scan = write_scan(tmp_path, 3)
    out = tmp_path / "data"
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    command = [sys.executable, "-m", "gpnerf_core", "data", "prepare-scannet", str(scan), "--out", str(out)]
    ok = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert f"wrote 3 of 3 frames of {SCENE}" in ok.stdout
    assert sorted(p.name for p in (out / SCENE / "color").iterdir()) == ["0.jpg", "1.jpg", "2.jpg"]
    (scan / f"{SCENE}.sens").unlink()
    failed = subprocess.run(command + ["--overwrite"], capture_output=True, text=True, env=env, timeout=120)
    assert failed.returncode == 2
    expected = f"error: {scan / f'{SCENE}.sens'}: missing; expected the scan's RGB-D stream from the ScanNet release"
    assert failed.stderr.strip() == expected
