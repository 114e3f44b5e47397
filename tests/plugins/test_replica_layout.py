"""The Replica (Semantic-NeRF render) layout reader on small fixtures written in the exact layout."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.replica.layout import (
    ReplicaSequence,
    every_nth_split,
    hfov_intrinsics,
    read_replica_sequence,
)

H, W = 12, 16


def _pose(k: int) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, 3] = (0.1 * k, -0.2 * k, 1.0 + k)
    return c2w


def _png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def write_sequence(root: Path, numbers=(0, 1, 2, 10), instance: bool = True, size=(H, W)) -> Path:
    """A tiny sequence: frame k has depth k + 1 metres plus a per-pixel ramp (mm), labels k + pixel % 7."""
    rng = np.random.default_rng(0)
    h, w = size
    for k, n in enumerate(numbers):
        _png(root / "rgb" / f"rgb_{n}.png", rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        depth = (1000 * (k + 1) + np.arange(h * w).reshape(h, w) * 37).astype(np.uint16)
        _png(root / "depth" / f"depth_{n}.png", depth)
        labels = ((np.arange(h * w).reshape(h, w) + k) % 7).astype(np.uint8)
        _png(root / "semantic_class" / f"semantic_class_{n}.png", labels)
        if instance:
            _png(root / "semantic_instance" / f"semantic_instance_{n}.png", labels.astype(np.uint16) * 1000)
    rows = [" ".join(f"{v:.6f}" for v in _pose(n).reshape(-1)) for n in numbers]
    (root / "traj_w_c.txt").write_text("\n".join(rows) + "\n")
    return root


@pytest.fixture
def seq_dir(tmp_path: Path) -> Path:
    return write_sequence(tmp_path / "office_0" / "Sequence_1")


def test_frames_sorted_numerically_and_decoded_with_dtypes(seq_dir):
    seq = ReplicaSequence(seq_dir)
    assert [f.number for f in seq.files] == [0, 1, 2, 10]  # not the lexicographic 0, 1, 10, 2
    frame = seq.load_frame(3)
    assert frame.rgb.dtype == torch.float32 and frame.rgb.shape == (H, W, 3)
    assert 0.0 <= float(frame.rgb.min()) and float(frame.rgb.max()) <= 1.0
    assert frame.depth.dtype == torch.float32 and frame.semantic.dtype == torch.int64
    assert frame.instance is not None and frame.instance.dtype == torch.int64
    # the 4th pose row belongs to rgb_10, the 4th frame in numeric order
    assert torch.allclose(frame.c2w, torch.from_numpy(_pose(10)).float())
    raw = np.asarray(Image.open(seq_dir / "rgb" / "rgb_10.png"))
    assert torch.equal(frame.rgb, torch.from_numpy(raw.astype(np.float32) / 255.0))


def test_depth_round_trips_exactly_in_millimetres(seq_dir):
    seq = ReplicaSequence(seq_dir)
    for index, number in enumerate((0, 1, 2, 10)):
        png = np.asarray(Image.open(seq_dir / "depth" / f"depth_{number}.png"))
        assert png.dtype == np.uint16
        mm = np.rint(seq.load_frame(index).depth.numpy().astype(np.float64) * 1000).astype(np.uint16)
        assert np.array_equal(mm, png)


def test_intrinsics_from_horizontal_fov_at_loaded_resolution(seq_dir):
    scene = read_replica_sequence(seq_dir)
    k = scene.intrinsics[0]
    assert math.isclose(float(k[0, 0]), W / 2, rel_tol=1e-6) and math.isclose(float(k[1, 1]), W / 2, rel_tol=1e-6)
    assert float(k[0, 2]) == (W - 1) / 2 and float(k[1, 2]) == (H - 1) / 2
    assert scene.intrinsics.shape == (4, 3, 3) and (scene.height, scene.width) == (H, W)
    k60 = hfov_intrinsics(480, 640, 60.0)
    assert math.isclose(k60[0, 0], 640 / (2 * math.tan(math.radians(30))))
    assert (k60[0, 2], k60[1, 2]) == (319.5, 239.5)


def test_resize_uses_nearest_labels_and_rescaled_intrinsics(seq_dir):
    seq = ReplicaSequence(seq_dir, size=(H // 2, W // 2))
    frame = seq.load_frame(0)
    assert frame.rgb.shape == (H // 2, W // 2, 3) and frame.depth.shape == (H // 2, W // 2)
    full = ReplicaSequence(seq_dir).load_frame(0)
    # nearest picks source pixel floor((i + 0.5) * 2) = 2 i + 1
    assert torch.equal(frame.depth, full.depth[1::2, 1::2])
    assert torch.equal(frame.semantic, full.semantic[1::2, 1::2])
    assert torch.equal(frame.instance, full.instance[1::2, 1::2])
    assert math.isclose(float(frame.intrinsics[0, 0]), W / 4, rel_tol=1e-6)
    assert float(frame.intrinsics[0, 2]) == (W // 2 - 1) / 2
    assert float(frame.rgb.min()) >= 0.0 and float(frame.rgb.max()) <= 1.0


def test_label_map_and_ignore(seq_dir):
    # raw ids 0..6: 0 -> ignore (mapped to 255), 1 -> 0, 2 -> 1, 3 -> 2, ids >= 4 are past the map -> ignore
    seq = ReplicaSequence(seq_dir, label_map=np.array([255, 0, 1, 2]), ignore_index=255)
    frame = seq.load_frame(0)
    raw = np.asarray(Image.open(seq_dir / "semantic_class" / "semantic_class_0.png")).astype(np.int64)
    expected = np.where(raw == 1, 0, np.where(raw == 2, 1, np.where(raw == 3, 2, 255)))
    assert np.array_equal(frame.semantic.numpy(), expected)
    assert set(np.unique(frame.semantic.numpy())) == {0, 1, 2, 255}
    unmapped = ReplicaSequence(seq_dir).load_frame(0)
    assert np.array_equal(unmapped.semantic.numpy(), raw)


def test_instance_is_none_without_its_folder(tmp_path):
    seq = ReplicaSequence(write_sequence(tmp_path / "s", instance=False))
    assert seq.load_frame(0).instance is None


def test_split_lists_and_rules(seq_dir):
    scene = read_replica_sequence(seq_dir, split=([0, 1, 3], [2]), near=0.5, far=4.0, name="office_0")
    assert (scene.train_frames, scene.eval_frames, scene.name) == ((0, 1, 3), (2,), "office_0")
    assert (scene.near, scene.far) == (0.5, 4.0)
    ruled = read_replica_sequence(seq_dir, split=functools.partial(every_nth_split, every=2))
    assert (ruled.train_frames, ruled.eval_frames) == ((0, 2), (1, 3))
    assert read_replica_sequence(seq_dir).name == "office_0/Sequence_1"
    assert every_nth_split(12, 6) == ((0, 1, 2, 4, 5, 6, 7, 8, 10, 11), (3, 9))
    with pytest.raises(ConfigError, match="both train_frames and eval_frames"):
        read_replica_sequence(seq_dir, split=([0, 1], [1]))
    with pytest.raises(ConfigError, match="index 9"):
        read_replica_sequence(seq_dir, split=([0, 9], []))


def _break(name: str, root: Path) -> str:
    """Damage a valid sequence in one way; return the file name the error must mention."""
    if name == "missing_folder":
        return str(root / "nope")
    if name == "missing_traj":
        (root / "traj_w_c.txt").unlink()
        return "traj_w_c.txt"
    if name == "short_traj_line":
        lines = (root / "traj_w_c.txt").read_text().splitlines()
        lines[1] = " ".join(lines[1].split()[:15])
        (root / "traj_w_c.txt").write_text("\n".join(lines) + "\n")
        return "traj_w_c.txt:2"
    if name == "nan_pose":
        lines = (root / "traj_w_c.txt").read_text().splitlines()
        lines[2] = lines[2].replace("1.000000", "nan", 1)
        (root / "traj_w_c.txt").write_text("\n".join(lines) + "\n")
        return "traj_w_c.txt:3"
    if name == "missing_depth":
        (root / "depth" / "depth_2.png").unlink()
        return "depth_2.png"
    if name == "missing_label":
        (root / "semantic_class" / "semantic_class_10.png").unlink()
        return "semantic_class_10.png"
    if name == "size_mismatch":
        _png(root / "depth" / "depth_1.png", np.zeros((H, W + 2), dtype=np.uint16))
        return "depth_1.png"
    if name == "pose_count":
        lines = (root / "traj_w_c.txt").read_text().splitlines()
        (root / "traj_w_c.txt").write_text("\n".join(lines[:-1]) + "\n")
        return "traj_w_c.txt"
    if name == "non_numeric_name":
        (root / "rgb" / "rgb_0.png").rename(root / "rgb" / "rgb_first.png")
        return "rgb_first.png"
    raise AssertionError(name)


@pytest.mark.parametrize(
    "case",
    ["missing_folder", "missing_traj", "short_traj_line", "nan_pose", "missing_depth", "missing_label",
     "size_mismatch", "pose_count", "non_numeric_name"],
)
def test_bad_input_raises_data_error_naming_the_file(seq_dir, case):
    target = _break(case, seq_dir)
    path = target if case == "missing_folder" else seq_dir
    with pytest.raises(DataError) as info:
        ReplicaSequence(path)
    message = str(info.value)
    assert target in message
    assert "\n" not in message and "expected" in message


def test_wrong_dtype_at_load_time_names_the_file(seq_dir):
    _png(seq_dir / "depth" / "depth_0.png", np.zeros((H, W, 3), dtype=np.uint8))
    seq = ReplicaSequence(seq_dir)
    with pytest.raises(DataError, match="depth_0.png"):
        seq.load_frame(0)
