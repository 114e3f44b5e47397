"""The ScanNet (Semantic-Ray export) dataset and its checker on tiny scenes written in the exact layout."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.scannet.dataset import ScanNetScenes, check_scannet_layout, read_split
from gpnerf_plugins.datasets.scannet.labels import SCANNET20_CLASS_NAMES
from gpnerf_plugins.datasets.scannet.scene import frame_split

COLOR_HW = (48, 64)  # colour images, like ScanNet's 968 x 1296 scaled down
DEPTH_HW = (24, 32)  # depth at half the colour resolution, like ScanNet's 480 x 640
K_COLOR = np.array([[50.0, 0.0, 31.5, 0.0], [0.0, 52.0, 23.5, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
# raw id -> nyu40id: 1 wall, 2 floor, 3 -> 39 otherfurniture, 5 -> 13 (not benchmarked), 7 -> 36 bathtub, 40 -> 40
TSV_ROWS = [(1, 1), (2, 2), (3, 39), (5, 13), (7, 36), (40, 40)]
EXPECTED_CLASS = {0: 255, 1: 0, 2: 1, 3: 19, 5: 255, 7: 18, 40: 255, 999: 255}
RAW_IDS = (0, 1, 2, 3, 5, 7, 40)


def pose_of(number: int) -> np.ndarray:
    c2w = np.eye(4)
    angle = 0.1 * number
    c2w[:3, :3] = [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]]
    c2w[:3, 3] = (0.25 * number, -0.5, 1.0 + 0.125 * number)
    return c2w


def raw_labels(number: int, unknown: bool = False) -> np.ndarray:
    """16 x 16 blocks of raw ids cycling through RAW_IDS, shifted per frame; optionally one block of id 999."""
    h, w = COLOR_HW
    blocks = (np.arange(h // 16)[:, None] * 4 + np.arange(w // 16)[None, :] + number) % len(RAW_IDS)
    labels = np.asarray(RAW_IDS, dtype=np.uint16)[np.kron(blocks, np.ones((16, 16), dtype=np.int64))]
    if unknown:
        labels[:16, :16] = 999
    return labels


def instance_ids(number: int) -> np.ndarray:
    """8-bit instance ids 0..16 at colour resolution, changing from pixel to pixel (so a resize's picks show)."""
    h, w = COLOR_HW
    return ((np.arange(h)[:, None] * 5 + np.arange(w)[None, :] * 3 + number) % 17).astype(np.uint8)


def depth_mm(number: int) -> np.ndarray:
    h, w = DEPTH_HW
    return (1000 + 100 * number + np.arange(h * w).reshape(h, w) * 3).astype(np.uint16)


def color_of(number: int) -> np.ndarray:
    h, w = COLOR_HW
    rng = np.random.default_rng(number)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def write_matrix(path: Path, matrix: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in matrix))


def write_png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def write_tsv(root: Path, rows=TSV_ROWS) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    path = root / "scannetv2-labels.combined.tsv"
    lines = ["id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass"]
    lines += [f"{raw}\tthing{raw}\tthing{raw}\t10\t{nyu}\t1\tx" for raw, nyu in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_instances(scene: Path, numbers) -> None:
    """``instance-filt/<n>.png`` (8-bit, colour resolution) for frames ``numbers``."""
    for n in numbers:
        write_png(scene / "instance-filt" / f"{n}.png", instance_ids(n))


def write_scene(root: Path, name: str, numbers=(0, 1, 2, 9, 10), invalid=(), unknown=(), instances=()) -> Path:
    """A scene in the real layout; ``instances``: the frames that get an ``instance-filt`` PNG (none: no folder)."""
    scene = root / name
    write_instances(scene, instances)
    for n in numbers:
        (scene / "color").mkdir(parents=True, exist_ok=True)
        Image.fromarray(color_of(n)).save(scene / "color" / f"{n}.jpg", quality=95)
        write_png(scene / "depth" / f"{n}.png", depth_mm(n))
        write_png(scene / "label-filt" / f"{n}.png", raw_labels(n, unknown=n in unknown))
        write_matrix(scene / "pose" / f"{n}.txt", np.full((4, 4), -np.inf) if n in invalid else pose_of(n))
    write_matrix(scene / "intrinsic" / "intrinsic_color.txt", K_COLOR)
    depth_intrinsics(root, name)  # the colour camera at the depth size: registration gives the plain resize
    return scene


@pytest.fixture
def root(tmp_path: Path) -> Path:
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00")
    write_scene(tmp_path, "scene0160_00", numbers=(0, 1, 2, 3))
    return tmp_path


def dataset(root: Path, **kwargs) -> ScanNetScenes:
    options = dict(root=str(root), height=COLOR_HW[0], width=COLOR_HW[1], scenes=["scene0000_00"])
    options.update(kwargs)
    return ScanNetScenes(**options)


# ----------------------------------------------------------------------------------------------------- splits


def test_shipped_splits_match_the_reference_lists_and_train_test_are_disjoint():
    train, test, val = read_split("train"), read_split("test"), read_split("val")
    assert len(train) == 198 and len(set(train)) == 198
    assert "scene0001_00" not in train and "scene0160_00" not in train
    assert train[0] == "scene0000_00" and train[-1] == "scene0199_00"
    assert test == (
        "scene0160_00", "scene0204_00", "scene0211_00", "scene0217_00", "scene0218_00",
        "scene0225_00", "scene0227_00", "scene0340_01", "scene0376_02", "scene0643_00",
    )  # fmt: skip
    assert not set(train) & set(test)
    assert val == ("scene0200_00", "scene0226_00", "scene0211_00")
    assert set(val) & set(test) == {"scene0211_00"}  # documented overlap inherited from the reference


def test_default_splits_are_the_shipped_files_and_missing_scenes_fail_by_name(root):
    data = ScanNetScenes(root=str(root))
    with pytest.raises(DataError, match=r"scene0002_00: missing \(197 of the 198 scenes of the train split"):
        data.scenes("train")
    with pytest.warns(UserWarning, match="197 of the 198"):
        assert ScanNetScenes(root=str(root), allow_missing_scenes=True).scenes("train") == ("scene0000_00",)
    with pytest.warns(UserWarning, match="9 of the 10"):
        assert ScanNetScenes(root=str(root), allow_missing_scenes=True).scenes("unseen") == ("scene0160_00",)
    with pytest.raises(DataError, match="none is present"):
        ScanNetScenes(root=str(root), allow_missing_scenes=True, unseen_scenes=["scene0999_00"]).scenes("unseen")
    with pytest.raises(DataError, match=r"scene0999_00: missing \(1 of the 1 scenes .* holds: [^)]*scene0000_00"):
        ScanNetScenes(root=str(root), scenes=["scene0999_00"]).scenes("train")
    with pytest.raises(ConfigError, match="'scene0000_00' is in both dataset.scenes and dataset.unseen_scenes"):
        ScanNetScenes(root=str(root), scenes=["scene0000_00"], unseen_scenes=["scene0000_00"])
    with pytest.raises(ConfigError, match="dataset.root is empty"):
        ScanNetScenes().scenes("train")
    with pytest.raises(ConfigError, match="unknown split"):
        data.scenes("val")


# ------------------------------------------------------------------------------------------- frames and values


def test_frames_numeric_order_poses_and_native_values(root):
    scene = dataset(root).load_scene("scene0000_00")
    assert scene.num_frames == 5 and (scene.height, scene.width) == COLOR_HW
    for index, number in enumerate((0, 1, 2, 9, 10)):  # frame 10 after 9, not after 1
        assert torch.allclose(scene.c2w[index], torch.from_numpy(pose_of(number)).float(), atol=1e-6)
    frame = scene.load_frame(4)
    assert torch.equal(frame.c2w, scene.c2w[4])
    decoded = np.asarray(Image.open(root / "scene0000_00" / "color" / "10.jpg"), dtype=np.float32) / 255.0
    assert frame.rgb.dtype == torch.float32 and torch.equal(frame.rgb, torch.from_numpy(decoded))
    # depth 24x32 -> 48x64 by nearest neighbour: each millimetre value fills a 2x2 block, divided by 1000
    expected_depth = np.kron(depth_mm(10), np.ones((2, 2))).astype(np.float32) / 1000.0
    assert torch.equal(frame.depth, torch.from_numpy(expected_depth))
    assert frame.semantic.dtype == torch.int64
    expected = np.vectorize(EXPECTED_CLASS.get)(raw_labels(10))
    assert torch.equal(frame.semantic, torch.from_numpy(expected))
    assert set(np.unique(expected)) == {0, 1, 18, 19, 255}


def test_intrinsics_scaled_by_the_true_ratios_per_axis(root):
    half = dataset(root, height=24, width=32).load_scene("scene0000_00")
    k = half.intrinsics[0].double()
    # fx, fy by exactly 1/2; principal point keeps pixel centres at integers: c' = s (c + 0.5) - 0.5
    assert torch.allclose(k, torch.tensor([[25.0, 0.0, 15.5], [0.0, 26.0, 11.5], [0.0, 0.0, 1.0]], dtype=torch.float64))
    squashed = dataset(root, height=24, width=48).load_scene("scene0000_00")  # sx = 0.75, sy = 0.5
    k = squashed.intrinsics[0].double()
    assert torch.allclose(k, torch.tensor([[37.5, 0.0, 23.5], [0.0, 26.0, 11.5], [0.0, 0.0, 1.0]], dtype=torch.float64))
    frame = squashed.load_frame(0)
    assert frame.rgb.shape == (24, 48, 3) and frame.depth.shape == (24, 48) and frame.semantic.shape == (24, 48)
    assert torch.equal(frame.intrinsics, squashed.intrinsics[0])


def test_resized_depth_and_labels_are_nearest_and_colour_is_antialiased(root):
    frame = dataset(root, height=24, width=32).load_scene("scene0000_00").load_frame(1)
    assert torch.equal(frame.depth, torch.from_numpy(depth_mm(1).astype(np.float32) / 1000.0))  # same size: exact
    labels = np.vectorize(EXPECTED_CLASS.get)(raw_labels(1))
    assert torch.equal(frame.semantic, torch.from_numpy(labels[1::2, 1::2]))  # centres of 2x2 cells
    full = np.asarray(Image.open(root / "scene0000_00" / "color" / "1.jpg"), dtype=np.float32) / 255.0
    box = full.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3))
    # antialiased: much closer to the 2x2 averages of noisy pixels than picking one pixel of each cell is
    error = float(np.abs(frame.rgb.numpy() - box).mean())
    assert error < 0.4 * min(float(np.abs(full[dy::2, dx::2] - box).mean()) for dy in (0, 1) for dx in (0, 1))


def test_invalid_pose_frames_are_dropped_with_their_images_and_a_warning(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", numbers=(0, 1, 2, 9, 10), invalid=(1, 9))
    with pytest.warns(UserWarning, match="dropped 2 of 5 frames whose pose is not finite"):
        scene = dataset(tmp_path).load_scene("scene0000_00")
    assert scene.num_frames == 3 and torch.isfinite(scene.c2w).all()
    for index, number in enumerate((0, 2, 10)):
        assert torch.allclose(scene.c2w[index], torch.from_numpy(pose_of(number)).float(), atol=1e-6)
        decoded = np.asarray(Image.open(tmp_path / "scene0000_00" / "color" / f"{number}.jpg"), np.float32) / 255
        assert torch.equal(scene.load_frame(index).rgb, torch.from_numpy(decoded))  # images follow their poses


def test_unknown_label_ids_become_ignore_with_one_warning_per_scene(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", numbers=(0, 1, 2), unknown=(0, 1))
    scene = dataset(tmp_path).load_scene("scene0000_00")
    with pytest.warns(UserWarning, match=r"256 label pixels of frame 0 have ids 999 .* mapped to ignore \(255\)"):
        frame = scene.load_frame(0)
    assert (frame.semantic[:16, :16] == 255).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene.load_frame(1)  # same scene: not reported again


# ----------------------------------------------------------------------------------------------- protocols


def test_heldout_eval_positions_are_numeric_and_disjoint_from_training():
    tokens = [str(i) for i in range(250)]
    train, held = frame_split(tokens, "heldout")
    assert held == (2, 22, 42, 62, 82, 102, 122, 142, 162, 182)
    assert not set(train) & set(held) and sorted(train + held) == list(range(250))
    assert frame_split(tokens[:2], "heldout") == ((0, 1), ())


def test_paper_parity_takes_lexicographic_positions_and_keeps_the_reference_leak():
    tokens = [str(i) for i in range(25)]
    # lexicographic: 0 1 10 11 ... 19 2 20 21 22 23 24 3 4 5 6 7 8 9
    train, held = frame_split(tokens, "paper_parity")
    assert held == (7, 10)  # positions 2 ("10") and 22 ("7")
    assert train == (0, 2, 3, 6, 9, 11, 14, 17, 22)  # positions 0, 3, ..., 24
    tokens = [str(i) for i in range(250)]
    train, held = frame_split(tokens, "paper_parity")
    lexicographic = sorted(tokens)
    assert set(train) & set(held) == {int(lexicographic[p]) for p in (42, 102, 162)}
    with pytest.raises(ConfigError, match="protocol"):
        frame_split(tokens, "random")


def test_scene_frame_lists_follow_the_protocol(root):
    heldout = dataset(root).load_scene("scene0000_00")  # frames 0 1 2 9 10
    assert heldout.eval_frames == (2,) and heldout.train_frames == (0, 1, 3, 4)
    parity = dataset(root, protocol="paper_parity").load_scene("scene0000_00")  # lexicographic 0 1 10 2 9
    assert parity.eval_frames == (4,) and parity.train_frames == (0, 2)
    assert (parity.near, parity.far) == (0.1, 6.0)
    with pytest.raises(ConfigError, match="protocol"):
        ScanNetScenes(root=str(root), protocol="paper")
    with pytest.raises(ConfigError, match="near"):
        ScanNetScenes(root=str(root), near=7.0)


# --------------------------------------------------------------------------------------------- bad inputs


def _first_error(root: Path, **kwargs) -> str:
    with pytest.raises(DataError) as info:
        scene = dataset(root, **kwargs).load_scene("scene0000_00")
        for index in range(scene.num_frames):
            scene.load_frame(index)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_missing_label_map_names_the_path_and_the_release(tmp_path):
    write_scene(tmp_path, "scene0000_00")
    message = _first_error(tmp_path)
    assert str(tmp_path / "scannetv2-labels.combined.tsv") in message and "ScanNet release" in message
    assert "download-scannet.py --label_map" in message


@pytest.mark.parametrize(
    "text, found",
    [
        ("id\tcategory\n1\twall\n", "header column 'nyu40id'"),
        ("id\tnyu40id\n1\twall\n", ":2: expected an integer in column 'nyu40id'"),
        ("id\tnyu40id\n1\t41\n", ":2: expected an NYU40 id in 0..40"),
        ("id\tnyu40id\n1\t1\n1\t2\n", ":3: expected each id listed once"),
    ],
)
def test_malformed_label_map_names_file_and_line(tmp_path, text, found):
    write_scene(tmp_path, "scene0000_00")
    (tmp_path / "scannetv2-labels.combined.tsv").write_text(text)
    message = _first_error(tmp_path)
    assert "scannetv2-labels.combined.tsv" in message and found in message


def test_label_map_file_option_is_used(tmp_path):
    write_scene(tmp_path, "scene0000_00")
    tsv = write_tsv(tmp_path / "meta")
    scene = dataset(tmp_path, label_map_file=str(tsv)).load_scene("scene0000_00")
    expected = np.vectorize(EXPECTED_CLASS.get)(raw_labels(0))
    assert torch.equal(scene.load_frame(0).semantic, torch.from_numpy(expected))


def _break(scene: Path, what: str) -> tuple[str, str]:
    """Damage one file of a written scene; returns (path fragment, message fragment) the error must contain."""
    if what == "missing depth":
        (scene / "depth" / "9.png").unlink()
        return "depth/9.png (frame 9)", "expected a file beside color/9.jpg, found nothing"
    if what == "non-numeric name":
        Image.fromarray(color_of(0)).save(scene / "color" / "frame_a.jpg")
        return "color/frame_a.jpg", "expected a numeric frame name"
    if what == "pose not 4x4":
        (scene / "pose" / "1.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
        return "pose/1.txt (frame 1)", "found 3 rows of [3] numbers"
    if what == "pose not numbers":
        (scene / "pose" / "1.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 one 0\n0 0 0 1\n")
        return "pose/1.txt (frame 1)", "the non-number 'one'"
    if what == "pose last row":
        write_matrix(scene / "pose" / "2.txt", np.ones((4, 4)))
        return "pose/2.txt (frame 2)", "found last row 1 1 1 1"
    if what == "pose not rigid":
        sheared = np.eye(4)
        sheared[0, 1] = 0.3
        write_matrix(scene / "pose" / "2.txt", sheared)
        return "pose/2.txt (frame 2)", "found rotation not orthonormal (max |R^T R - I| = 0.3)"
    if what == "pose mirrored":
        write_matrix(scene / "pose" / "2.txt", np.diag([1.0, 1.0, -1.0, 1.0]))
        return "pose/2.txt (frame 2)", "found rotation determinant -1 (a mirror)"
    if what == "missing intrinsic":
        (scene / "intrinsic" / "intrinsic_color.txt").unlink()
        return "intrinsic/intrinsic_color.txt", "found nothing"
    if what == "truncated colour":
        data = (scene / "color" / "10.jpg").read_bytes()
        (scene / "color" / "10.jpg").write_bytes(data[: len(data) // 2])
        return "color/10.jpg (frame 10)", "expected a complete JPEG colour image"
    if what == "truncated label":
        data = (scene / "label-filt" / "2.png").read_bytes()
        (scene / "label-filt" / "2.png").write_bytes(data[: len(data) // 2])
        return "label-filt/2.png (frame 2)", "expected a complete label PNG"
    if what == "colour size":
        Image.fromarray(color_of(1)[:40]).save(scene / "color" / "1.jpg")
        return "color/1.jpg (frame 1)", "expected 64x48 (WxH)"
    if what == "depth aspect":
        write_png(scene / "depth" / "2.png", depth_mm(2)[:, :12])
        return "depth/2.png (frame 2)", "expected 32x24 (WxH) like 0.png, the size intrinsic/intrinsic_depth.txt describes"
    if what == "rgb label":
        write_png(scene / "label-filt" / "1.png", color_of(1))
        return "label-filt/1.png (frame 1)", "expected a single-channel integer label PNG, found mode RGB"
    if what == "missing instance":
        write_instances(scene, (0, 1, 2))  # instance-filt/ exists but lacks frames 9 and 10: the lower is named
        return "instance-filt/9.png (frame 9)", (
            "expected a file beside color/9.jpg (instance-filt/ exists, so every frame needs one), found nothing"
        )
    if what.endswith("instance") and not (scene / "instance-filt").exists():
        write_instances(scene, (0, 1, 2, 9, 10))  # every frame's, then one damaged
    if what == "rgb instance":
        write_png(scene / "instance-filt" / "2.png", color_of(2))
        return "instance-filt/2.png (frame 2)", "expected a single-channel integer instance PNG, found mode RGB"
    if what == "truncated instance":
        data = (scene / "instance-filt" / "0.png").read_bytes()
        (scene / "instance-filt" / "0.png").write_bytes(data[: len(data) // 2])
        return "instance-filt/0.png (frame 0)", "expected a complete instance PNG"
    if what == "narrow instance":
        write_png(scene / "instance-filt" / "1.png", instance_ids(1)[:, :40])
        return "instance-filt/1.png (frame 1)", "found 40x48"
    raise AssertionError(what)


BREAKAGES = [
    "missing depth", "non-numeric name", "pose not 4x4", "pose not numbers", "pose last row", "pose not rigid", "pose mirrored",
    "missing intrinsic",
    "truncated colour", "truncated label", "colour size", "depth aspect", "rgb label",
    "missing instance", "rgb instance", "truncated instance", "narrow instance",
]  # fmt: skip


@pytest.mark.parametrize("what", BREAKAGES)
def test_every_bad_file_is_a_one_line_data_error_naming_it(tmp_path, what):
    write_tsv(tmp_path)
    scene = write_scene(tmp_path, "scene0000_00")
    path_fragment, message_fragment = _break(scene, what)
    message = _first_error(tmp_path)
    assert path_fragment in message and message_fragment in message


# ------------------------------------------------------------------------------------------- instance ids


def test_instance_ids_are_read_as_stored_and_resized_by_nearest_like_labels(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", instances=(0, 1, 2, 9, 10))
    write_scene(tmp_path, "scene0160_00", numbers=(0, 1))  # no instance-filt/: no instance ids
    scene = dataset(tmp_path).load_scene("scene0000_00")
    frame = scene.load_frame(4)  # frame 10
    assert frame.instance is not None and frame.instance.dtype == torch.int64
    assert torch.equal(frame.instance, torch.from_numpy(instance_ids(10).astype(np.int64)))  # colour size: as stored
    assert int(frame.instance.min()) == 0  # 0 (not annotated) is kept as an id, not remapped
    half = dataset(tmp_path, height=24, width=32).load_scene("scene0000_00").load_frame(3)  # frame 9
    assert half.instance.shape == (24, 32)
    assert torch.equal(half.instance, torch.from_numpy(instance_ids(9)[1::2, 1::2].astype(np.int64)))  # cell centres
    # the same nearest picks as the labels at an uneven size: an instance map holding the raw label ids maps onto
    # exactly the loaded classes
    write_png(tmp_path / "scene0000_00" / "instance-filt" / "2.png", raw_labels(2).astype(np.uint8))
    squashed = dataset(tmp_path, height=24, width=48).load_scene("scene0000_00").load_frame(2)
    mapped = np.vectorize(EXPECTED_CLASS.get)(squashed.instance.numpy())
    assert torch.equal(squashed.semantic, torch.from_numpy(mapped))
    assert len(np.unique(squashed.instance.numpy())) == len(RAW_IDS)
    plain = dataset(tmp_path, scenes=["scene0160_00"]).load_scene("scene0160_00")
    assert all(plain.load_frame(i).instance is None for i in range(plain.num_frames))


def test_instance_ids_follow_their_frame_when_invalid_poses_are_dropped(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", invalid=(1,), instances=(0, 1, 2, 9, 10))
    with pytest.warns(UserWarning, match="dropped 1 of 5"):
        scene = dataset(tmp_path).load_scene("scene0000_00")
    for index, number in enumerate((0, 2, 9, 10)):
        assert torch.equal(scene.load_frame(index).instance, torch.from_numpy(instance_ids(number).astype(np.int64)))


def test_scene_missing_one_instance_file_fails_at_load_naming_it(tmp_path):
    write_tsv(tmp_path)
    scene = write_scene(tmp_path, "scene0000_00", instances=(0, 1, 2, 10))
    with pytest.raises(DataError) as info:
        dataset(tmp_path).load_scene("scene0000_00")  # at load, not when frame 9 is first decoded
    expected = (
        f"{scene / 'instance-filt' / '9.png'} (frame 9): expected a file beside color/9.jpg "
        "(instance-filt/ exists, so every frame needs one), found nothing"
    )
    assert str(info.value) == expected


def test_scene_without_valid_poses_is_an_error(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", numbers=(0, 1), invalid=(0, 1))
    with pytest.warns(UserWarning), pytest.raises(DataError, match="at least one frame with a finite pose"):
        dataset(tmp_path).load_scene("scene0000_00")


# ------------------------------------------------------------------------------------------------ checker


def test_checker_counts_notes_and_exact_histogram(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", numbers=(0, 1, 2), invalid=(1,), unknown=(2,))
    report = check_scannet_layout(tmp_path, histogram_every=1)
    assert report.ok, report.format()
    assert report.present["scenes"] == 1 and report.present["color"] == 3 and report.present["invalid poses"] == 1
    expected = np.zeros(256, dtype=np.int64)
    for n in (0, 1, 2):
        expected += np.bincount(np.vectorize(EXPECTED_CLASS.get)(raw_labels(n, unknown=n == 2)).ravel(), minlength=256)
    for class_id, name in enumerate(SCANNET20_CLASS_NAMES):
        assert report.class_histogram[name] == expected[class_id], name
    assert report.class_histogram["ignore"] == expected[255]
    assert sum(report.class_histogram.values()) == 3 * COLOR_HW[0] * COLOR_HW[1]
    notes = "\n".join(report.notes)
    assert "1 of 3 frames have an invalid (non-finite) pose" in notes
    assert "256 label pixels have ids absent from the label map (999)" in notes
    assert "train split: 1 of its 198 scenes present" in notes


def test_checker_reports_every_problem_with_frame_expected_and_found(tmp_path):
    scene = write_scene(tmp_path, "scene0000_00")
    (tmp_path / "scannetv2-labels.combined.tsv").write_text("id\tcategory\n1\twall\n")
    expected = [_break(scene, what) for what in ("missing depth", "non-numeric name", "pose not 4x4", "pose last row",
                                                 "missing intrinsic", "truncated colour", "truncated label",
                                                 "missing instance", "truncated instance", "narrow instance")]
    report = check_scannet_layout(tmp_path)
    lines = [str(p) for p in report.problems]
    assert not report.ok
    for path_fragment, message_fragment in expected:
        assert any(path_fragment in line and message_fragment in line for line in lines), (path_fragment, lines)
    assert any("scannetv2-labels.combined.tsv:1" in line and "header column 'nyu40id'" in line for line in lines)
    assert report.class_histogram == {}


def test_checker_counts_instance_files_and_reports_a_missing_one(tmp_path):
    write_tsv(tmp_path)
    write_scene(tmp_path, "scene0000_00", instances=(0, 1, 2, 9, 10))
    write_scene(tmp_path, "scene0160_00", numbers=(0, 1))
    report = check_scannet_layout(tmp_path)
    assert report.ok, report.format()
    assert report.present["instance-filt"] == 5
    assert "instance maps (instance-filt/, optional): 1 of 2 scenes" in report.notes
    (tmp_path / "scene0000_00" / "instance-filt" / "2.png").unlink()
    (tmp_path / "scene0000_00" / "instance-filt" / "77.png").write_bytes(b"")  # no colour image: a note
    report = check_scannet_layout(tmp_path)
    assert [str(p) for p in report.problems] == [
        f"{tmp_path / 'scene0000_00' / 'instance-filt' / '2.png'} (frame 2): expected a file beside color/2.jpg "
        "(instance-filt/ exists, so every frame needs one), found nothing"
    ]
    assert report.present["instance-filt"] == 5
    assert "scene0000_00: 1 instance-filt/ files without a colour image (ignored by the loader)" in report.notes


def test_checker_without_instance_maps_counts_none_and_reports_nothing(root):
    report = check_scannet_layout(root)
    assert report.ok and "instance-filt" not in report.present
    assert "instance maps (instance-filt/, optional): 0 of 2 scenes" in report.notes


def test_checker_without_scenes_reports_it(tmp_path):
    write_tsv(tmp_path)
    (tmp_path / "notes").mkdir()
    report = check_scannet_layout(tmp_path)
    assert [str(p) for p in report.problems] == [f"{tmp_path}: expected sceneXXXX_YY scene folders, found none"]
    assert any("ignored 1 folders" in note for note in report.notes)


def _data_check(root: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    command = [sys.executable, "-m", "gpnerf_core", "data", "check", str(root), "--layout", "scannet"]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)


def test_data_check_command_exits_0_then_1(root):
    good = _data_check(root)
    assert good.returncode == 0, good.stdout + good.stderr
    assert "problems: none" in good.stdout and "class histogram" in good.stdout
    (root / "scene0160_00" / "pose" / "3.txt").unlink()
    bad = _data_check(root)
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert "scene0160_00/pose/3.txt (frame 3): expected a file beside color/3.jpg, found nothing" in bad.stdout


# ----------------------------------------------------------------------------------------------------- pipeline


def test_scannet_trains_and_evaluates_through_the_unchanged_pipeline(root, tmp_path):
    from pipeline_check import assert_both_splits_scored, train_and_evaluate

    metrics = train_and_evaluate(
        ["dataset=scannet", f"dataset.root={root}", "dataset.height=32", "dataset.width=48",
         "dataset.scenes=[scene0000_00]", "dataset.unseen_scenes=[scene0160_00]"],
        tmp_path / "run",
    )
    assert_both_splits_scored(metrics, 20)


def test_instance_head_trains_and_evaluates_on_scannet_instance_maps(tmp_path):
    from gpnerf_core.model.build import build_components
    from gpnerf_core.config.compose import compose
    from gpnerf_core.runtime.distributed import Distributed
    from gpnerf_core.evaluation.evaluator import evaluate
    from pipeline_check import TINY_MODEL, make_trainer

    root = tmp_path / "data"
    write_tsv(root)
    write_scene(root, "scene0000_00", instances=(0, 1, 2, 9, 10))
    write_scene(root, "scene0160_00", numbers=(0, 1, 2, 3), instances=(0, 1, 2, 3))
    cfg = compose(
        ["+head=instance", "+loss=instance", "head.slots=20", *TINY_MODEL, "dataset=scannet", f"dataset.root={root}",
         "dataset.height=32", "dataset.width=48", "dataset.scenes=[scene0000_00]",
         "dataset.unseen_scenes=[scene0160_00]"]
    )  # fmt: skip
    torch.manual_seed(0)
    components = build_components(cfg)
    trainer = make_trainer(cfg, tmp_path / "run", components=components)
    assert trainer.fit(progress=False).steps == 2
    metrics = evaluate(cfg, components, trainer.frames, tmp_path / "run", Distributed.single())
    for split in ("train_heldout", "unseen"):
        assert 0.0 <= metrics["eval"][split]["instance/ap_matched@0.75"] <= 1.0, metrics["eval"][split]



# ------------------------------------------------------------------------------------------- depth registration
def depth_intrinsics(root: Path, scene: str, shift_rows: float = 0.0) -> np.ndarray:
    """``intrinsic_depth.txt``: the colour intrinsics at the depth size, principal point moved down by ``shift_rows``."""
    sx, sy = DEPTH_HW[1] / COLOR_HW[1], DEPTH_HW[0] / COLOR_HW[0]
    k = K_COLOR.copy()
    k[0, 0], k[0, 2] = K_COLOR[0, 0] * sx, (K_COLOR[0, 2] + 0.5) * sx - 0.5
    k[1, 1], k[1, 2] = K_COLOR[1, 1] * sy, (K_COLOR[1, 2] + 0.5) * sy - 0.5 + shift_rows
    write_matrix(root / scene / "intrinsic" / "intrinsic_depth.txt", k)
    return k


def test_depth_is_registered_with_its_own_intrinsics(root):
    (root / "scene0000_00" / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.warns(UserWarning, match="intrinsic_depth.txt: missing; depth is resized"):
        reference = dataset(root).load_scene("scene0000_00").load_frame(1).depth
    resized = dataset(root, depth_alignment="resize").load_scene("scene0000_00").load_frame(1).depth
    assert torch.equal(reference, resized)
    depth_intrinsics(root, "scene0000_00")  # depth K = colour K at the depth size: registration = resize
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        consistent = dataset(root).load_scene("scene0000_00").load_frame(1).depth
    assert torch.equal(consistent, resized)
    depth_intrinsics(root, "scene0000_00", shift_rows=1.0)  # the depth camera's centre one depth row lower
    shifted = dataset(root).load_scene("scene0000_00").load_frame(1).depth
    assert torch.equal(shifted[:-2], resized[2:])  # one depth row = two output rows
    assert torch.all(shifted[-2:] == 0)  # outside the depth image: unknown
    with pytest.raises(ConfigError, match="dataset.depth_alignment='nearest'; expected one of: intrinsics, resize"):
        dataset(root, depth_alignment="nearest")
