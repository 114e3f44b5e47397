"""The ``replica`` and ``replica_instance`` datasets and their checkers, on tiny fixtures in the exact layouts."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.replica.dataset import (
    ReplicaInstanceScenes,
    ReplicaInstanceScenesConfig,
    ReplicaScenes,
    ReplicaScenesConfig,
    check_replica_instance_layout,
    check_replica_layout,
)
from gpnerf_plugins.datasets.replica.classes import (
    CLASS_NAMES,
    IGNORE_INDEX,
    RAW_CLASS_NAMES,
    VALID_RAW_IDS,
    raw_to_class_table,
)
from gpnerf_plugins.datasets.replica.splits import read_split_file

H, W = 24, 32
# raw ids: 3 -> class 0 (basket), 7 -> 1 (bed), 93 -> 47 (wall), 98 -> 50 (rug); 0 (other) and 50 (mat) -> ignore
LABEL_TILE = np.array([3, 7, 93, 98, 0, 50], dtype=np.uint8)
SMALL_EVAL = dict(eval_start=2, eval_stop=700, eval_step=2, eval_count=2)  # held-out positions 2 and 4


def pose(number: int, scene: int = 0) -> np.ndarray:
    """A distinct camera-to-world per frame: rotation about y by 0.1 rad per frame, translation by frame and scene."""
    angle = 0.1 * number
    c2w = np.eye(4)
    c2w[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    c2w[:3, 3] = (0.25 * number, -0.5 * scene, 1.0 + 0.125 * number)
    return c2w


def png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def make_frames(numbers, scene: int = 0, size=(H, W)) -> dict:
    """Deterministic content of frames ``numbers``: rgb, depth (mm), raw class ids, instance ids and pose."""
    rng = np.random.default_rng(len(numbers) + 10 * scene)
    h, w = size
    frames = {}
    for k, n in enumerate(numbers):
        raw = np.resize(np.roll(LABEL_TILE, k), (h, w)).astype(np.uint8)
        frames[n] = dict(
            rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            depth=(1000 * (k + 1) + np.arange(h * w).reshape(h, w) * 3).astype(np.uint16),
            raw=raw,
            instance=(raw.astype(np.uint16) * 10 + k).astype(np.uint16),
            c2w=pose(n, scene),
        )
    return frames


def write_frames(folder: Path, numbers, *, scene: int = 0, semantic=True, instance=False, size=(H, W)) -> dict:
    """Write ``make_frames`` plus traj_w_c.txt (row k = pose of the k-th number); returns what was written."""
    frames = make_frames(numbers, scene, size)
    for n, frame in frames.items():
        png(folder / "rgb" / f"rgb_{n}.png", frame["rgb"])
        png(folder / "depth" / f"depth_{n}.png", frame["depth"])
        if semantic:
            png(folder / "semantic_class" / f"semantic_class_{n}.png", frame["raw"])
            png(folder / "semantic_class" / f"vis_sem_class_{n}.png", frame["rgb"])  # Semantic-NeRF ships these; unread
        if instance:
            png(folder / "semantic_instance" / f"semantic_instance_{n}.png", frame["instance"])
    rows = [" ".join(f"{v:.9f}" for v in frame["c2w"].reshape(-1)) for frame in frames.values()]
    (folder / "traj_w_c.txt").write_text("\n".join(rows) + "\n")
    return frames


@pytest.fixture
def replica_root(tmp_path: Path) -> Path:
    """office_1 (a heldout training scene) with two 6-frame sequences; office_0 (a test scene) numbered 0, 1, 2, 10."""
    root = tmp_path / "Replica"
    write_frames(root / "office_1" / "Sequence_1", range(6), scene=1)
    write_frames(root / "office_1" / "Sequence_2", range(6), scene=2)
    write_frames(root / "office_0" / "Sequence_1", (0, 1, 2, 10), scene=0, instance=True)
    return root


@pytest.fixture
def instance_root(tmp_path: Path) -> Path:
    """DM-NeRF layout: office_0 without semantic_class, room_0 with it; 6 frames each."""
    root = tmp_path / "Replica_DM"
    write_frames(root / "office_0", range(6), scene=0, semantic=False, instance=True)
    write_frames(root / "room_0", range(6), scene=3, semantic=True, instance=True)
    return root


def replica(root: Path, **kwargs) -> ReplicaScenes:
    return ReplicaScenes(root=str(root), **{"height": 0, "width": 0, **SMALL_EVAL, **kwargs})


def instance_dataset(root: Path, **kwargs) -> ReplicaInstanceScenes:
    rule = dict(eval_start=2, eval_stop=6, eval_step=4, train_stop=6, train_step=2)  # eval (2,), pool (0, 2, 4)
    return ReplicaInstanceScenes(root=str(root), **{"height": 0, "width": 0, **rule, **kwargs})


# ---------------------------------------------------------------------------------------------------- class map


def test_class_table_and_51_class_mapping():
    assert len(RAW_CLASS_NAMES) == 102 and RAW_CLASS_NAMES[0] == "other" and RAW_CLASS_NAMES[93] == "wall"
    assert len(VALID_RAW_IDS) == 51 == len(set(VALID_RAW_IDS)) and len(CLASS_NAMES) == 51 == len(set(CLASS_NAMES))
    assert VALID_RAW_IDS[:4] == (3, 7, 8, 10) and VALID_RAW_IDS[-4:] == (93, 95, 97, 98)
    assert CLASS_NAMES[:3] == ("basket", "bed", "bench") and CLASS_NAMES[-4:] == ("wall", "wall-plug", "window", "rug")
    table = raw_to_class_table()
    assert table.shape == (102,)
    assert (table[3], table[7], table[93], table[98]) == (0, 1, 47, 50)
    assert all(table[i] == IGNORE_INDEX for i in range(102) if i not in VALID_RAW_IDS)
    assert sorted(table[list(VALID_RAW_IDS)].tolist()) == list(range(51))


# ---------------------------------------------------------------------------------------------------- splits


def test_split_files_ship_in_the_package():
    assert read_split_file("replica_test.txt") == ("office_0", "room_0")
    assert read_split_file("replica_train.txt") == ("office_1", "office_2", "office_3", "office_4", "room_1", "room_2")
    all_eight = {f"office_{i}" for i in range(5)} | {f"room_{i}" for i in range(3)}
    assert set(read_split_file("replica_paper_train.txt")) == all_eight
    assert read_split_file("replica_paper_test.txt") == ("office_0", "room_0")
    assert read_split_file("replica_instance.txt") == tuple(sorted(all_eight - {"office_1"}))


def sequence_folders(root: Path, scenes, sequences=("Sequence_1", "Sequence_2")) -> Path:
    """Empty ``<scene>/Sequence_<n>/`` folders: enough for ``scenes()``, which only lists them."""
    for scene in scenes:
        for sequence in sequences:
            (root / scene / sequence).mkdir(parents=True)
    return root


ALL_EIGHT = [f"office_{i}" for i in range(5)] + [f"room_{i}" for i in range(3)]


def test_heldout_scenes_are_disjoint_and_use_both_sequences(tmp_path):
    dataset = ReplicaScenes(root=str(sequence_folders(tmp_path, ALL_EIGHT)))
    train, unseen = dataset.scenes("train"), dataset.scenes("unseen")
    assert unseen == ("office_0/Sequence_1", "room_0/Sequence_1")
    assert len(train) == 12 and {n.split("/")[1] for n in train} == {"Sequence_1", "Sequence_2"}
    assert {n.split("/")[0] for n in train} == {"office_1", "office_2", "office_3", "office_4", "room_1", "room_2"}
    assert not {n.split("/")[0] for n in train} & {n.split("/")[0] for n in unseen}
    with pytest.raises(ConfigError, match="unknown split"):
        dataset.scenes("val")


def test_paper_parity_reproduces_the_scene_leak(tmp_path):
    with pytest.warns(UserWarning, match="office_0, room_0"):
        dataset = ReplicaScenes(root=str(sequence_folders(tmp_path, ALL_EIGHT)), protocol="paper_parity")
    train = dataset.scenes("train")
    assert len(train) == 16
    assert set(dataset.scenes("unseen")) <= set(train)  # the leak: unseen sequences are trained on


def test_unknown_protocol_lists_the_choices():
    for cls in (ReplicaScenes, ReplicaInstanceScenes):
        with pytest.raises(ConfigError, match="heldout, paper_parity"):
            cls(protocol="paper")


def test_default_frame_rules_match_the_reference_positions_and_stay_disjoint():
    train, held = ReplicaScenes().frame_split(900)
    assert held == tuple(range(2, 183, 20))  # [2:700:20][:10]
    assert not set(train) & set(held) and sorted(train + held) == list(range(900))

    train, held = ReplicaInstanceScenes().frame_split(900)
    assert held == tuple(range(600, 881, 20))  # [0:900:20][30:]
    assert train == tuple(i for i in range(0, 900, 2) if i not in held) and not set(train) & set(held)
    with pytest.warns(UserWarning, match="evaluation frames"):
        parity = ReplicaInstanceScenes(protocol="paper_parity")
    train, held = parity.frame_split(900)
    assert train == tuple(range(0, 900, 2)) and set(held) <= set(train)  # the reference's overlap (C7)


def test_bad_settings_are_config_errors():
    with pytest.raises(ConfigError, match="near"):
        ReplicaScenes(near=2.0, far=1.0)
    with pytest.raises(ConfigError, match="height"):
        ReplicaScenes(height=0, width=320)
    with pytest.raises(ConfigError, match="eval_step"):
        ReplicaScenes(eval_step=0)
    with pytest.raises(ConfigError, match="train_step"):
        ReplicaInstanceScenes(train_step=0)
    with pytest.raises(ConfigError, match="hfov"):
        ReplicaInstanceScenes(hfov_deg=180.0)


def test_configs_are_structured_and_match_the_constructors():
    import inspect

    for config, cls, name in (
        (ReplicaScenesConfig, ReplicaScenes, "replica"),
        (ReplicaInstanceScenesConfig, ReplicaInstanceScenes, "replica_instance"),
    ):
        node = OmegaConf.structured(config)
        assert node.name == name
        fields = {
            f.name: f.default if f.default is not dataclasses.MISSING else tuple(f.default_factory())
            for f in dataclasses.fields(config)
            if f.name != "name"
        }
        params = {k: p.default for k, p in inspect.signature(cls).parameters.items()}
        assert fields == params


def test_a_registry_builds_both_datasets_from_config_nodes(replica_root):
    from gpnerf_core.registry.components import ComponentSpec, Registry
    from gpnerf_core.registry.plugins import PluginInfo

    registry = Registry()
    for name, cls, config in (
        ("replica", ReplicaScenes, ReplicaScenesConfig),
        ("replica_instance", ReplicaInstanceScenes, ReplicaInstanceScenesConfig),
    ):
        registry.add("dataset", ComponentSpec(name, cls, config), PluginInfo("test", "test", "0"))
        assert not registry.problems
        assert isinstance(registry.build("dataset", OmegaConf.structured(config)), cls)
    overrides = {"root": str(replica_root), "height": 12, "width": 16}
    node = OmegaConf.merge(OmegaConf.structured(ReplicaScenesConfig), overrides)
    scene = registry.build("dataset", node).load_scene("office_1/Sequence_1")
    assert (scene.height, scene.width) == (12, 16) and scene.eval_frames == (2,)  # 6 frames: [2:700:20][:10]


# ---------------------------------------------------------------------------------------------------- replica loading


def test_frames_load_value_by_value(replica_root):
    dataset = replica(replica_root)
    scene = dataset.load_scene("office_1/Sequence_2")
    written = make_frames(range(6), scene=2)
    assert scene.name == "office_1/Sequence_2" and (scene.height, scene.width) == (H, W)
    assert scene.eval_frames == (2, 4) and scene.train_frames == (0, 1, 3, 5)
    assert (scene.near, scene.far) == (0.1, 10.0)
    for index in range(6):
        frame = scene.load_frame(index)
        expected = written[index]
        assert torch.allclose(scene.c2w[index], torch.from_numpy(expected["c2w"]).float(), atol=1e-7)
        assert torch.equal(frame.c2w, scene.c2w[index])
        assert torch.equal(frame.rgb, torch.from_numpy(expected["rgb"].astype(np.float32) / 255.0))
        # depth: uint16 millimetres -> float metres, exactly
        assert torch.allclose(frame.depth.double(), torch.from_numpy(expected["depth"] / 1000.0), atol=1e-6)
        assert torch.equal(frame.semantic, torch.from_numpy(raw_to_class_table()[expected["raw"]]))
        assert frame.instance is None  # no semantic_instance folder in this sequence
    labels = scene.load_frame(0).semantic
    assert set(labels.unique().tolist()) == {0, 1, 47, 50, IGNORE_INDEX}
    assert int((labels == IGNORE_INDEX).sum()) == 2 * H * W // 6  # raw 0 and 50


def test_numeric_frame_order_and_instances(replica_root):
    scene = replica(replica_root).load_scene("office_0/Sequence_1")
    written = make_frames((0, 1, 2, 10), scene=0)
    frame = scene.load_frame(3)  # rgb_10 is the 4th frame, after rgb_2 (lexicographic order would put it 3rd)
    assert torch.equal(frame.rgb, torch.from_numpy(written[10]["rgb"].astype(np.float32) / 255.0))
    assert torch.allclose(frame.c2w, torch.from_numpy(pose(10)).float(), atol=1e-7)
    assert torch.equal(scene.load_frame(2).c2w, torch.from_numpy(pose(2)).float())
    assert torch.equal(frame.instance, torch.from_numpy(written[10]["instance"].astype(np.int64)))


def test_intrinsics_follow_the_hfov_at_the_loaded_size(replica_root):
    # C5: at 320x240 the reference uses fx=320, cx=320, fy=319.5, cy=229.5 (640x480 values, swapped and 10 px off)
    scene = ReplicaScenes(root=str(replica_root), **SMALL_EVAL).load_scene("office_1/Sequence_1")
    assert (scene.height, scene.width) == (240, 320)
    expected = torch.tensor([[160.0, 0.0, 159.5], [0.0, 160.0, 119.5], [0.0, 0.0, 1.0]])
    assert torch.equal(scene.intrinsics[0], expected) and scene.intrinsics.shape == (6, 3, 3)
    frame = scene.load_frame(1)
    assert frame.rgb.shape == (240, 320, 3) and frame.semantic.shape == (240, 320) and frame.depth.shape == (240, 320)
    assert torch.equal(frame.intrinsics, expected)

    small = replica(replica_root, height=12, width=16).load_scene("office_1/Sequence_1")
    assert torch.equal(small.intrinsics[0], torch.tensor([[8.0, 0.0, 7.5], [0.0, 8.0, 5.5], [0.0, 0.0, 1.0]]))
    # a resize that changes the aspect ratio scales fy by (12/24) / (32/32)
    squashed = replica(replica_root, height=12, width=32).load_scene("office_1/Sequence_1")
    assert torch.equal(squashed.intrinsics[0], torch.tensor([[16.0, 0.0, 15.5], [0.0, 8.0, 5.5], [0.0, 0.0, 1.0]]))
    # nearest-neighbour label resize keeps valid ids: every 2nd column of the 24x32 label map
    frame = small.load_frame(0)
    raw = np.resize(LABEL_TILE, (H, W))[1::2, 1::2]
    assert torch.equal(frame.semantic, torch.from_numpy(raw_to_class_table()[raw]))


def test_unknown_label_ids_raise_or_become_ignore(replica_root):
    path = replica_root / "office_1" / "Sequence_1" / "semantic_class" / "semantic_class_3.png"
    raw = np.asarray(Image.open(path)).copy()
    raw[0, :5] = 150
    png(path, raw)
    scene = replica(replica_root).load_scene("office_1/Sequence_1")
    scene.load_frame(2)  # other frames are fine
    with pytest.raises(DataError, match=r"semantic_class_3\.png: label ids \[150\]"):
        scene.load_frame(3)
    lenient = replica(replica_root, strict_labels=False).load_scene("office_1/Sequence_1").load_frame(3)
    assert (lenient.semantic[0, :5] == IGNORE_INDEX).all()
    assert torch.equal(lenient.semantic[1:], torch.from_numpy(raw_to_class_table()[raw[1:]]))


def test_loaded_scene_frames_are_disjoint_and_unknown_names_rejected(replica_root):
    dataset = replica(replica_root)
    scene = dataset.load_scene("office_0/Sequence_1")
    assert scene.eval_frames == (2,) and scene.train_frames == (0, 1, 3)
    assert dataset.load_scene("office_0/Sequence_1") is scene  # indexed once
    with pytest.raises(ConfigError, match="unknown scene 'office_0/Sequence_2'"):
        dataset.load_scene("office_0/Sequence_2")  # test scenes contribute Sequence_1 only


def test_missing_folders_are_named(replica_root, tmp_path):
    with pytest.raises(DataError, match=r"office_2: scene folder missing"):
        replica(replica_root).load_scene("office_2/Sequence_1")
    with pytest.warns(UserWarning):
        parity = replica(replica_root, protocol="paper_parity")
    with pytest.raises(ConfigError, match=r"'office_0/Sequence_2'; expected one of: office_0/Sequence_1$"):
        parity.load_scene("office_0/Sequence_2")
    with pytest.raises(ConfigError, match="dataset.root is empty"):
        ReplicaScenes().load_scene("office_1/Sequence_1")
    with pytest.raises(DataError, match="nowhere: dataset.root folder missing"):
        replica(tmp_path / "nowhere").load_scene("office_1/Sequence_1")


def test_relative_root_is_taken_from_the_working_directory(replica_root, monkeypatch):
    monkeypatch.chdir(replica_root.parent)
    scene = ReplicaScenes(root="Replica", height=0, width=0).load_scene("office_1/Sequence_1")
    assert scene.num_frames == 6


# ---------------------------------------------------------------------------------------------------- bad inputs


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _set_traj_line(folder: Path, line: int, text: str) -> None:
    lines = (folder / "traj_w_c.txt").read_text().splitlines()
    lines[line] = text
    (folder / "traj_w_c.txt").write_text("\n".join(lines) + "\n")


# name -> (damage(folder), file named in the loader's DataError and the checker's problem)
DAMAGES = {
    "missing label": (lambda f: (f / "semantic_class" / "semantic_class_3.png").unlink(), "semantic_class_3.png"),
    "missing depth": (lambda f: (f / "depth" / "depth_1.png").unlink(), "depth_1.png"),
    "size mismatch": (lambda f: png(f / "depth" / "depth_4.png", np.zeros((H, W - 2), np.uint16)), "depth_4.png"),
    "truncated png": (lambda f: _truncate(f / "rgb" / "rgb_2.png"), "rgb_2.png"),
    "traj line count": (lambda f: _set_traj_line(f, 5, ""), "traj_w_c.txt"),
    "non-numeric frame": (lambda f: png(f / "rgb" / "rgb_x.png", np.zeros((H, W, 3), np.uint8)), "rgb_x.png"),
    "nan pose": (lambda f: _set_traj_line(f, 2, " ".join(["nan"] * 16)), "traj_w_c.txt:3"),
    "inf pose": (lambda f: _set_traj_line(f, 4, " ".join(["1"] * 15 + ["inf"])), "traj_w_c.txt:5"),
    "sheared pose": (lambda f: _set_traj_line(f, 3, "1 0.3 0 0 0 1 0 0 0 0 1 0 0 0 0 1"), "traj_w_c.txt:4"),
    "mirrored pose": (lambda f: _set_traj_line(f, 1, "1 0 0 0 0 1 0 0 0 0 -1 0 0 0 0 1"), "traj_w_c.txt:2"),
    "scaled pose": (lambda f: _set_traj_line(f, 0, "2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1"), "traj_w_c.txt:1"),
    "unknown label id": (
        lambda f: png(f / "semantic_class" / "semantic_class_5.png", np.full((H, W), 200, np.uint8)),
        "semantic_class_5.png",
    ),
}


def _load_all(scene) -> None:
    for index in range(scene.num_frames):
        scene.load_frame(index)


@pytest.mark.parametrize("case", sorted(DAMAGES))
def test_replica_bad_input_is_a_one_line_data_error_naming_the_file(replica_root, case):
    damage, named = DAMAGES[case]
    damage(replica_root / "office_1" / "Sequence_1")
    with pytest.raises(DataError) as info:
        _load_all(replica(replica_root).load_scene("office_1/Sequence_1"))
    message = str(info.value)
    assert named in message and "\n" not in message
    _load_all(replica(replica_root).load_scene("office_1/Sequence_2"))  # the other sequence is untouched


@pytest.mark.parametrize("case", sorted(DAMAGES))
def test_replica_checker_reports_each_damage(replica_root, case):
    assert check_replica_layout(replica_root).ok
    damage, named = DAMAGES[case]
    damage(replica_root / "office_1" / "Sequence_1")
    report = check_replica_layout(replica_root)
    assert not report.ok
    assert any(named in str(problem) for problem in report.problems), report.format()
    assert all("Sequence_1" in p.path and "office_1" in p.path for p in report.problems)


def test_replica_checker_counts_and_histogram(replica_root):
    report = check_replica_layout(replica_root)
    assert report.ok, report.format()
    assert report.present == {
        "scenes": 2,
        "sequences": 3,
        "rgb": 16,
        "poses": 16,
        "depth": 16,
        "semantic_class": 16,
        "semantic_instance": 4,
    }
    expected = dict.fromkeys(CLASS_NAMES, 0)
    expected["ignore"] = 0
    table = raw_to_class_table()
    for numbers, scene in ((range(6), 1), (range(6), 2), ((0, 1, 2, 10), 0)):  # the three sequences of the fixture
        for frame in make_frames(numbers, scene).values():
            ids, counts = np.unique(table[frame["raw"]], return_counts=True)
            for class_id, count in zip(ids.tolist(), counts.tolist()):
                expected["ignore" if class_id == IGNORE_INDEX else CLASS_NAMES[class_id]] += count
    assert report.class_histogram == {name: count for name, count in expected.items() if count}
    assert set(report.class_histogram) == {"basket", "bed", "wall", "rug", "ignore"}
    assert any(note.startswith("classes without a labelled pixel (47): bench, bin,") for note in report.notes)
    assert report.class_histogram["wall"] == 16 * H * W // 6 and report.class_histogram["ignore"] == 2 * 16 * H * W // 6
    assert any("absent" in note and "room_0" in note for note in report.notes)


def test_replica_checker_reports_every_problem_at_once(replica_root):
    seq = replica_root / "office_1" / "Sequence_1"
    for case in ("missing label", "truncated png", "nan pose", "unknown label id"):
        DAMAGES[case][0](seq)
    (replica_root / "office_2" / "rgb").mkdir(parents=True)  # DM-NeRF layout by mistake
    report = check_replica_layout(replica_root)
    text = "\n".join(str(p) for p in report.problems)
    named_files = ("semantic_class_3.png (frame 3)", "rgb_2.png (frame 2)", "traj_w_c.txt:3 (frame 2)")
    for named in (*named_files, "semantic_class_5.png (frame 5)"):
        assert named in text, text
    assert "expected Replica class ids 0..101, found ids 200" in text
    assert "office_2: expected Sequence_<n>/ folders" in text and "--layout replica_instance" in text
    assert len(report.problems) == 5


def test_cli_check_exit_codes(replica_root):
    env = {**os.environ, "GPNERF_DISABLE_PLUGIN_AUTOLOAD": "1"}
    command = [sys.executable, "-m", "gpnerf_core", "data", "check", str(replica_root), "--layout", "replica"]
    good = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert good.returncode == 0, good.stdout + good.stderr
    assert "problems: none" in good.stdout and "wall" in good.stdout
    _truncate(replica_root / "office_0" / "Sequence_1" / "depth" / "depth_10.png")
    bad = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert "depth_10.png (frame 10): expected a readable PNG" in bad.stdout


# ---------------------------------------------------------------------------------------------------- replica_instance


def test_instance_scenes_load_raw_instances_and_optional_semantics(instance_root):
    dataset = instance_dataset(instance_root)
    assert dataset.scenes("unseen") == () and "room_1" in dataset.scenes("train")
    office = dataset.load_scene("office_0")
    written = make_frames(range(6), scene=0)
    assert office.train_frames == (0, 4) and office.eval_frames == (2,)  # even positions minus evaluation frames
    assert (office.near, office.far) == (0.1, 6.0)
    for index in range(6):
        frame = office.load_frame(index)
        assert torch.equal(frame.instance, torch.from_numpy(written[index]["instance"].astype(np.int64)))
        assert frame.instance.dtype == torch.int64
        assert (frame.semantic == IGNORE_INDEX).all() and frame.semantic.dtype == torch.int64
        assert torch.allclose(frame.depth.double(), torch.from_numpy(written[index]["depth"] / 1000.0), atol=1e-6)
        assert torch.equal(frame.rgb, torch.from_numpy(written[index]["rgb"].astype(np.float32) / 255.0))
        assert torch.allclose(frame.c2w, torch.from_numpy(pose(index, 0)).float(), atol=1e-7)
    room = dataset.load_scene("room_0").load_frame(1)
    written = make_frames(range(6), scene=3)
    assert torch.equal(room.semantic, torch.from_numpy(raw_to_class_table()[written[1]["raw"]]))

    resized = instance_dataset(instance_root, height=12, width=16).load_scene("room_0")
    assert torch.equal(resized.intrinsics[0], torch.tensor([[8.0, 0.0, 7.5], [0.0, 8.0, 5.5], [0.0, 0.0, 1.0]]))
    frame = resized.load_frame(0)
    assert frame.instance.shape == (12, 16) and frame.semantic.shape == (12, 16)


def test_instance_paper_parity_keeps_the_overlap(instance_root):
    with pytest.warns(UserWarning):
        dataset = instance_dataset(instance_root, protocol="paper_parity")
    scene = dataset.load_scene("office_0")
    assert scene.train_frames == (0, 2, 4) and scene.eval_frames == (2,)


def _renumber_from_one(folder: Path) -> None:
    for kind in ("rgb", "depth", "semantic_instance"):
        for n in range(5, -1, -1):
            (folder / kind / f"{kind}_{n}.png").rename(folder / kind / f"{kind}_{n + 1}.png")


INSTANCE_DAMAGES = {
    "missing instance": (
        lambda f: (f / "semantic_instance" / "semantic_instance_3.png").unlink(),
        "semantic_instance_3.png",
    ),
    "size mismatch": (
        lambda f: png(f / "semantic_instance" / "semantic_instance_1.png", np.zeros((H - 1, W), np.uint16)),
        "semantic_instance_1.png",
    ),
    "truncated png": (lambda f: _truncate(f / "depth" / "depth_5.png"), "depth_5.png"),
    "traj line count": (lambda f: _set_traj_line(f, 0, ""), "traj_w_c.txt"),
    "non-numeric frame": (lambda f: png(f / "rgb" / "rgb_a.png", np.zeros((H, W, 3), np.uint8)), "rgb_a.png"),
    "nan pose": (lambda f: _set_traj_line(f, 1, " ".join(["nan"] * 16)), "traj_w_c.txt:2"),
    "numbered from one": (_renumber_from_one, "rgb_0.png"),
}


@pytest.mark.parametrize("case", sorted(INSTANCE_DAMAGES))
def test_instance_bad_input_is_a_data_error_and_a_checker_problem(instance_root, case):
    assert check_replica_instance_layout(instance_root).ok
    damage, named = INSTANCE_DAMAGES[case]
    damage(instance_root / "office_0")
    with pytest.raises(DataError) as info:
        _load_all(instance_dataset(instance_root).load_scene("office_0"))
    assert named in str(info.value) and "\n" not in str(info.value)
    report = check_replica_instance_layout(instance_root)
    assert any(named in str(problem) for problem in report.problems), report.format()
    assert all("office_0" in p.path for p in report.problems)


def test_instance_unknown_class_ids_and_checker_summary(instance_root):
    report = check_replica_instance_layout(instance_root)
    assert report.ok, report.format()
    assert report.present == dict(scenes=2, rgb=12, poses=12, depth=12, semantic_instance=12, semantic_class=6)
    assert sum(report.class_histogram.values()) == 6 * H * W  # only room_0 has class labels
    assert report.class_histogram["rug"] == H * W  # raw 98 is one id of the six-id tile
    assert any(note.endswith("office_0: 36 distinct instance ids") for note in report.notes)  # 6 raw ids x 6 frames
    png(instance_root / "room_0" / "semantic_class" / "semantic_class_2.png", np.full((H, W), 120, np.uint8))
    with pytest.raises(DataError, match=r"semantic_class_2\.png: label ids \[120\]"):
        instance_dataset(instance_root).load_scene("room_0").load_frame(2)
    damaged = check_replica_instance_layout(instance_root)
    assert [p.frame for p in damaged.problems] == ["2"] and damaged.class_histogram["ignore"] > 0


def test_instance_checker_flags_the_semantic_nerf_layout(replica_root):
    report = check_replica_instance_layout(replica_root)
    assert [Path(p.path).name for p in report.problems] == ["office_0", "office_1", report.root.name]
    assert all("--layout replica" in p.found for p in report.problems[:2])


# ---------------------------------------------------------------------------------------------------- pipeline


def test_replica_trains_and_evaluates_through_the_unchanged_pipeline(replica_root, tmp_path):
    from pipeline_check import assert_both_splits_scored, train_and_evaluate

    for index, scene in enumerate(("office_2", "office_3", "office_4", "room_1", "room_2")):
        for sequence in (1, 2):
            write_frames(replica_root / scene / f"Sequence_{sequence}", range(6), scene=3 + 2 * index + sequence)
    write_frames(replica_root / "room_0" / "Sequence_1", range(6), scene=20)
    metrics = train_and_evaluate(
        ["dataset=replica", f"dataset.root={replica_root}", "dataset.height=32", "dataset.width=48",
         "dataset.eval_step=2", "dataset.eval_count=2"],
        tmp_path / "run",
    )
    assert_both_splits_scored(metrics, 51)


def test_own_scenes_replace_the_shipped_lists_with_whatever_sequences_they_have(tmp_path):
    root = tmp_path / "mine"
    write_frames(root / "kitchen" / "Sequence_1", range(4), scene=1)
    write_frames(root / "kitchen" / "Sequence_3", range(4), scene=2)
    write_frames(root / "hall" / "Sequence_2", range(4), scene=0)
    dataset = ReplicaScenes(root=str(root), height=H, width=W, scenes=["kitchen"], unseen_scenes=["hall"])
    assert dataset.scenes("train") == ("kitchen/Sequence_1", "kitchen/Sequence_3")
    assert dataset.scenes("unseen") == ("hall/Sequence_2",)  # no Sequence_1: its lowest-numbered sequence
    assert dataset.load_scene("hall/Sequence_2").num_frames == 4
    with pytest.raises(DataError, match=r"attic: scene folder missing; .* holds: hall, kitchen$"):
        ReplicaScenes(root=str(root), scenes=["attic"]).scenes("train")


def test_own_scene_lists_are_checked():
    with pytest.raises(ConfigError, match="'hall' is in both dataset.scenes and dataset.unseen_scenes"):
        ReplicaScenes(scenes=["hall", "kitchen"], unseen_scenes=["hall"])
    assert ReplicaScenes(scenes=["office_0"]).test_scene_names == ("room_0",)  # trained on: no longer unseen
    with pytest.raises(ConfigError, match="dataset.scenes names 'hall' twice"):
        ReplicaScenes(scenes=["hall", "hall"])
    with pytest.raises(ConfigError, match="dataset.unseen_scenes has 'a/b'; expected folder names"):
        ReplicaInstanceScenes(unseen_scenes=["a/b"])


def test_unseen_scenes_null_is_the_shipped_list_and_empty_is_none():
    """Issue 55: null (the default) = the shipped unseen list less the scenes trained on, none when the trained
    scenes are the user's own (no shipped scene to read); [] = none."""
    assert ReplicaScenesConfig().unseen_scenes is None
    assert ReplicaScenes().test_scene_names == ("office_0", "room_0")
    assert ReplicaScenes(scenes=["office_0"]).test_scene_names == ("room_0",)
    assert ReplicaScenes(scenes=["office_1"]).test_scene_names == ("office_0", "room_0")
    assert ReplicaScenes(scenes=["kitchen"]).test_scene_names == ()  # the user's own: no shipped scene read
    assert ReplicaScenes(unseen_scenes=[]).test_scene_names == ()
    assert ReplicaScenes(scenes=["kitchen"], unseen_scenes=[]).test_scene_names == ()
    with pytest.raises(ConfigError, match=r"'kitchen' is in both .* \(dataset.unseen_scenes=\[\] for none\)"):
        ReplicaScenes(scenes=["kitchen"], unseen_scenes=["kitchen"])
    assert ReplicaInstanceScenes(scenes=["kitchen"]).unseen_scene_names == ()


def test_a_model_of_the_users_own_folder_evaluates_renders_and_exports_it_alone(tmp_path, monkeypatch):
    """Issue 55: a generalizable model trained on a Replica-layout folder holding only the user's scene was refused
    over office_0 (a shipped scene the folder never had) by run, render and export."""
    from pipeline_check import TINY_MODEL, in_process

    root = tmp_path / "mine"
    write_frames(root / "kitchen" / "Sequence_1", range(6), scene=1, size=(32, 48))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")
    data = ["dataset=replica", f"dataset.root={root}", "dataset.scenes=[kitchen]", "dataset.height=32",
            "dataset.width=48", "dataset.eval_step=2", "dataset.eval_count=2"]
    run = tmp_path / "run"
    assert in_process("run", "+head=unet", "+loss=dgs", *TINY_MODEL, "eval.save_images=0", *data,
                      f"out_dir={run}") == 0
    assert "unseen_scenes: null" in (run / "config.yaml").read_text()
    checkpoint = next((run / "checkpoints").glob("*.pt"))
    assert in_process("export", f"checkpoint={checkpoint}", f"out_dir={tmp_path / 'x'}", "threads=1") == 0
    assert (tmp_path / "x" / "points.ply").is_file()
    assert in_process("export", f"checkpoint={checkpoint}", "export.scene=kitchen/Sequence_1",
                      f"out_dir={tmp_path / 'x2'}", "threads=1") == 0
    assert in_process("render", f"checkpoint={checkpoint}", "render.frames=2", f"out_dir={tmp_path / 'r'}",
                      "threads=1") == 0


def test_own_instance_scenes(instance_root):
    dataset = ReplicaInstanceScenes(root=str(instance_root), height=H, width=W, scenes=["room_0"], unseen_scenes=["office_0"])
    assert dataset.scenes("train") == ("room_0",) and dataset.scenes("unseen") == ("office_0",)
    assert dataset.load_scene("office_0").num_frames == 6
