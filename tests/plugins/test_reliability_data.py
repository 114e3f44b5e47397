"""Issue 31, the data side: nothing lost, nothing silent, no traceback.

Every layout refuses what ``dataset.validate`` refuses (one shared implementation, ``gpnerf_core.data.checks``);
``quick`` reads what it needs to refuse a bad Replica label or an 8-bit depth map before training; a damaged file of the
embedded cache is found by its content hash and rendered again; ``eval`` of splits without frames is one line; an
absurd ``dataset.near``/``dataset.far`` is refused naming the key; a checkpoint's dataset options stay with its dataset.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from capture_fixtures import write_capture
from gpnerf_core.config.compose import compose
from gpnerf_core.config.overrides import foreign_dataset_note, merge_overrides
from gpnerf_core.data.base import check_depth_range
from gpnerf_core.data.checks import QUICK_FRAMES, frames_to_check
from gpnerf_core.engine.validation import check_data
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.evaluation.evaluator import check_splits_have_frames
from gpnerf_core.model.build import build_components
from gpnerf_core.types import Frame, Scene
from gpnerf_plugins.datasets import tools
from gpnerf_plugins.datasets.capture.dataset import CaptureScenes
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes
from gpnerf_plugins.datasets.replica.dataset import ReplicaScenes
from pipeline_check import TINY_MODEL

H, W = 24, 32
FRAMES = 6


def png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def pose(n: int) -> np.ndarray:
    """Cameras along x, turning 0.1 rad about y per frame, 1 m above the origin (a plausible Replica scale)."""
    c2w = np.eye(4)
    angle = 0.1 * n
    c2w[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    c2w[:3, 3] = (0.25 * n, -0.5, 1.0 + 0.125 * n)
    return c2w


def write_sequence(folder: Path) -> Path:
    """A Replica (Semantic-NeRF) sequence of ``FRAMES`` frames: depth 2 m, labels raw id 3 (basket)."""
    rng = np.random.default_rng(0)
    for n in range(FRAMES):
        png(folder / "rgb" / f"rgb_{n}.png", rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        png(folder / "depth" / f"depth_{n}.png", np.full((H, W), 2000, np.uint16))
        png(folder / "semantic_class" / f"semantic_class_{n}.png", np.full((H, W), 3, np.uint8))
    (folder / "traj_w_c.txt").write_text("".join(" ".join(f"{v:.9f}" for v in pose(n).ravel()) + "\n"
                                                 for n in range(FRAMES)))
    return folder


def set_pose_entry(folder: Path, row: int, entry: int, value: str) -> None:
    lines = (folder / "traj_w_c.txt").read_text().splitlines()
    values = lines[row].split()
    values[entry] = value
    lines[row] = " ".join(values)
    (folder / "traj_w_c.txt").write_text("\n".join(lines) + "\n")


@pytest.fixture
def replica_root(tmp_path: Path) -> Path:
    root = tmp_path / "Replica"
    write_sequence(root / "kitchen" / "Sequence_1")
    write_sequence(root / "hall" / "Sequence_1")
    return root


def replica(root: Path, **options) -> ReplicaScenes:
    return ReplicaScenes(root=str(root), scenes=["kitchen"], unseen_scenes=["hall"], height=0, width=0,
                         eval_step=2, eval_count=2, **options)


def far_and_far_away(sequence: Path) -> None:
    """Every depth map 30 m deep (beyond Replica's far = 10 m) and frame 3's camera 1e30 m away."""
    for n in range(FRAMES):
        png(sequence / "depth" / f"depth_{n}.png", np.full((H, W), 30000, np.uint16))
    set_pose_entry(sequence, 3, 3, "1e30")


# ------------------------------------------------------------------ 1. every layout checks what validation checks


def test_replica_data_check_refuses_a_far_away_camera_and_depth_beyond_far(replica_root, capsys):
    assert tools.check([str(replica_root), "--layout", "replica"]) == 0
    far_and_far_away(replica_root / "kitchen" / "Sequence_1")
    assert tools.check([str(replica_root), "--layout", "replica"]) == 1
    out = capsys.readouterr().out
    assert ("depth_0.png (frame 0): expected depth in the units of the poses and near/far (--far 10), found every "
            "known depth is beyond far=10 (nearest 30)") in out
    assert ("traj_w_c.txt (frame 3): expected poses in the units of near/far (--far 10), found camera centre 1e+30 m "
            "from the scene's median centre") in out


def test_quick_validation_refuses_the_same_as_data_check(replica_root):
    far_and_far_away(replica_root / "kitchen" / "Sequence_1")
    problems = replica(replica_root).check_files(["kitchen/Sequence_1"], "quick")
    assert any("frame 3: camera centre 1e+30 m from the scene's median centre" in p for p in problems), problems
    assert any("frame 0: every known depth is beyond far=10 (nearest 30)" in p for p in problems), problems


def write_scannet(root: Path) -> Path:
    """A ScanNet (Semantic-Ray export) folder: one scene of 4 frames, colour 48x64, depth 24x32 at 2 m, wall labels."""
    root.mkdir(parents=True)
    (root / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\n1\twall\twall\t10\t1\t1\tx\n")
    scene = root / "scene0000_00"
    rng = np.random.default_rng(0)
    for n in range(4):
        (scene / "color").mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(scene / "color" / f"{n}.jpg")
        png(scene / "depth" / f"{n}.png", np.full((24, 32), 2000, np.uint16))
        png(scene / "label-filt" / f"{n}.png", np.ones((48, 64), np.uint16))
        (scene / "pose").mkdir(exist_ok=True)
        np.savetxt(scene / "pose" / f"{n}.txt", pose(n))
    (scene / "intrinsic").mkdir()
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt",
               [[50.0, 0, 31.5, 0], [0, 50.0, 23.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    return scene


def test_scannet_data_check_refuses_a_far_away_camera_depth_beyond_far_and_8_bit_depth(tmp_path, capsys):
    scene = write_scannet(tmp_path / "scannet")
    assert tools.check([str(tmp_path / "scannet"), "--layout", "scannet"]) == 0
    png(scene / "depth" / "0.png", np.full((24, 32), 30000, np.uint16))  # frame 0: the decoded one of every 10
    far = pose(2)
    far[0, 3] = 1e30
    np.savetxt(scene / "pose" / "2.txt", far)
    png(scene / "depth" / "3.png", np.full((24, 32), 200, np.uint8))
    assert tools.check([str(tmp_path / "scannet"), "--layout", "scannet"]) == 1
    out = capsys.readouterr().out
    assert "depth/0.png (frame 0): expected depth in the units of the poses and near/far (--far 6), found every" in out
    assert "pose/2.txt (frame 2): expected poses in the units of near/far (--far 6), found camera centre 1e+30" in out
    assert "depth/3.png (frame 3): expected a 16-bit depth PNG (millimetres), found an 8-bit PNG" in out


# ------------------------------------------------------------------ 2. quick refuses a bad label or depth map in time


@pytest.mark.parametrize("damage, named", [
    (lambda s: png(s / "semantic_class" / "semantic_class_4.png", np.full((H, W), 200, np.uint8)),
     "semantic_class_4.png: label ids [200] are not Replica class ids; expected 0..101"),
    (lambda s: png(s / "depth" / "depth_5.png", np.full((H, W), 200, np.uint8)),
     "depth_5.png: an 8-bit PNG (at most 255 units: 0.255 m in millimetres); expected a 16-bit depth PNG"),
])
def test_quick_validation_refuses_a_bad_label_or_an_8_bit_depth_before_training(replica_root, damage, named):
    damage(replica_root / "kitchen" / "Sequence_1")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, "dataset=replica", f"dataset.root={replica_root}",
                   "dataset.scenes=[kitchen]", "dataset.unseen_scenes=[hall]", "dataset.height=32",
                   "dataset.width=48", "dataset.eval_step=2", "dataset.eval_count=2"])
    assert cfg.dataset.validate == "quick"
    with pytest.raises(DataError, match=r"dataset.validate=quick found 1 problem\(s\) before training") as error:
        check_data(cfg, build_components(cfg))
    assert named in str(error.value)


def test_quick_decodes_a_bounded_spread_of_frames_and_every_held_out_one():
    def scene(frames: int) -> Scene:
        held_out = tuple(range(1, frames, 100))
        return Scene("s", torch.eye(4).expand(frames, 4, 4), torch.eye(3).expand(frames, 3, 3), 4, 4, 0.1, 5.0,
                     tuple(i for i in range(frames) if i not in held_out), held_out, lambda i: None)

    assert frames_to_check(scene(5), "quick") == [0, 1, 2, 3, 4]
    picked = frames_to_check(scene(900), "quick")
    spread = [i for i in picked if i % 100 != 1]
    assert len(spread) == QUICK_FRAMES and picked[0] == 0 and picked[-1] == 899
    assert set(range(1, 900, 100)) <= set(picked)  # every held-out frame: evaluation reads each after training
    assert frames_to_check(scene(900), "full") == list(range(900))


# ------------------------------------------------------------------ 3. a damaged file of the embedded cache


def test_a_damaged_label_png_in_the_embedded_cache_is_found_by_its_hash_and_rendered_again(tmp_path, monkeypatch,
                                                                                             capsys):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    options = dict(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=4, height=16, width=24, eval_every=0)
    assert EmbeddedScenes(**options).check_files(["layout_00"], "quick") == []
    [cached] = (tmp_path / "cache" / "embedded_scenes").iterdir()
    label = cached / "layout_00" / "Sequence_1" / "semantic_class" / "semantic_class_1.png"
    original = label.read_bytes()
    damaged = bytearray(original)
    for i in range(len(damaged) // 2, len(damaged) // 2 + 4):
        damaged[i] ^= 0xFF  # same size: only the content hash tells
    label.write_bytes(bytes(damaged))
    capsys.readouterr()
    assert EmbeddedScenes(**options).check_files(["layout_00"], "quick") == []
    err = capsys.readouterr().err
    assert "note: the cached embedded scenes in" in err and "semantic_class_1.png: content differs" in err
    assert label.read_bytes() == original


# ------------------------------------------------------------------ 4. evaluation splits without frames


class Splits:
    """A dataset whose ``train`` scene holds out ``held`` frames and whose ``unseen`` split has no scene."""

    num_classes, ignore_index = 3, 255

    def __init__(self, held: tuple[int, ...]) -> None:
        self.held = held

    def scenes(self, split: str) -> tuple[str, ...]:
        return ("room",) if split == "train" else ()

    def load_scene(self, name: str) -> Scene:
        return Scene(name, torch.eye(4).expand(4, 4, 4), torch.eye(3).expand(4, 3, 3), 4, 4, 0.1, 5.0, (0, 1),
                     self.held, lambda i: None)


def _eval_cfg(splits):
    return OmegaConf.create({"eval": {"splits": splits}, "dataset": {"name": "capture", "root": "/data/room"}})


def test_splits_without_frames_are_refused_or_noted():
    with pytest.raises(ConfigError) as error:
        check_splits_have_frames(_eval_cfg(["train", "unseen"]), SimpleNamespace(dataset=Splits(())))
    assert str(error.value).startswith(
        "eval.splits=[train, unseen] select no frame of dataset 'capture' (dataset.root=/data/room): split 'train' has "
        "1 scene(s) and no evaluation frame in them; split 'unseen' has no scene; expected held-out frames")
    notes = check_splits_have_frames(_eval_cfg(["train", "unseen"]), SimpleNamespace(dataset=Splits((2, 3))))
    assert notes == ["split 'unseen' has no scene in dataset 'capture' (dataset.root=/data/room): unseen scores no "
                     "image"]
    with pytest.raises(ConfigError, match=r"eval.splits=\[\]: nothing to evaluate; expected some of train, unseen"):
        check_splits_have_frames(_eval_cfg([]), SimpleNamespace(dataset=Splits((2,))))


def gpnerf(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, GPNERF_CACHE=str(cwd / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def one_error_line(result: subprocess.CompletedProcess) -> str:
    lines = [line for line in result.stderr.splitlines() if line.strip() and "pybullet build time" not in line]
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def embedded_checkpoint(tmp_path_factory) -> Path:
    """One training step on the embedded scenes with dataset options of that dataset only (num_train_scenes, ...)."""
    workspace = tmp_path_factory.mktemp("reliability_data")
    tiny = ["+head=unet", "+loss=dgs", "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1",
            "dataset.frames_per_scene=6", "dataset.eval_every=3", "dataset.height=32", "dataset.width=48",
            *[o for o in TINY_MODEL if not o.startswith(("train.steps", "eval."))], "train.steps=1", "eval.splits=[]"]
    result = gpnerf("run", *tiny, f"out_dir={workspace / 'trained'}", cwd=workspace)
    assert result.returncode == 0, result.stderr[-2000:]
    return workspace / "trained" / "checkpoints" / "step_0000001.pt"


def test_eval_of_a_capture_without_evaluation_frames_is_one_line_and_leaves_nothing(embedded_checkpoint):
    workspace = embedded_checkpoint.parent.parent.parent
    scenes = EmbeddedScenes(root=str(workspace / "set"), num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=6,
                            height=32, width=48, eval_every=0)
    capture = write_capture(scenes.load_scene("layout_00"), workspace / "capture")
    out = workspace / "eval_capture"
    result = gpnerf("eval", f"checkpoint={embedded_checkpoint}", "dataset=capture", f"dataset.root={capture}",
                    "dataset.eval_every=0", "eval.splits=[train,unseen]", f"out_dir={out}", cwd=workspace)
    line = one_error_line(result)
    assert line.startswith(f"error: eval.splits=[train, unseen] select no frame of dataset 'capture' "
                           f"(dataset.root={capture}): split 'train' has 1 scene(s) and no evaluation frame"), line
    assert not out.exists()


def test_run_whose_evaluation_would_score_nothing_is_refused_before_training(tmp_path):
    out = tmp_path / "run"
    result = gpnerf("run", "+experiment=baselines/semantic_nerf", "dataset.scenes=[layout_00]",
                    "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=0", "dataset.frames_per_scene=6",
                    "dataset.eval_every=0", "dataset.height=32", "dataset.width=48", f"out_dir={out}", cwd=tmp_path)
    line = one_error_line(result)
    assert "select no frame of dataset 'embedded'" in line and "dataset.eval_every) or eval.splits" in line, line
    assert not out.exists()


# ------------------------------------------------------------------ 5. absurd near/far


@pytest.mark.parametrize("near, far, message", [
    (0.1, 1e30, "dataset.far=1e+30: expected a finite distance in (dataset.near=0.1, 1e+06] (metres)"),
    (0.1, math.inf, "dataset.far=inf: expected a finite distance"),
    (0.1, math.nan, "dataset.far=nan: expected a finite distance"),
    (-1.0, 5.0, "dataset.near=-1.0: expected a finite distance > 0 (metres)"),
    (0.0, 5.0, "dataset.near=0.0: expected a finite distance > 0 (metres)"),
    (5.0, 2.0, "dataset.near=5.0, dataset.far=2.0: expected near < far (metres)"),
    (2.0, 2.0, "dataset.near=2.0, dataset.far=2.0: expected near < far (metres)"),
])
def test_absurd_depth_ranges_are_refused_naming_the_key(near, far, message):
    with pytest.raises(ConfigError) as error:
        check_depth_range(near, far)
    assert str(error.value) == message or str(error.value).startswith(message)
    assert check_depth_range(0.1, 1e6) == (0.1, 1e6)


def test_data_check_refuses_a_far_of_1e30(replica_root):
    with pytest.raises(ConfigError, match=r"^--near 0.1 --far 1e\+30: expected 0 < near < far <= 1e\+06 \(metres\)$"):
        tools.check([str(replica_root), "--layout", "replica", "--far", "1e30"])


def test_far_1e30_is_refused_when_the_components_are_built():
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, "dataset.far=1e30"])
    with pytest.raises(ConfigError, match=r"^dataset.far=1e\+30: expected a finite distance"):
        build_components(cfg)


def test_a_captures_own_far_of_1e30_is_refused_naming_the_capture(tmp_path, monkeypatch):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    scenes = EmbeddedScenes(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=4, height=32, width=48,
                            eval_every=0)
    capture = write_capture(scenes.load_scene("layout_00"), tmp_path / "room")
    transforms = json.loads((capture / "transforms.json").read_text())
    for frame in transforms["frames"]:
        frame.update(near=0.1, far=1e30)
    (capture / "transforms.json").write_text(json.dumps(transforms))
    dataset = CaptureScenes(root=str(capture), height=32, width=48)
    with pytest.raises(DataError, match=r"capture 'room' \(.*transforms.json\): its depth bounds are near=0.1, "
                                        r"far=1e\+30 m .*expected 0 < near < far <= 1e\+06 m"):
        dataset.load_scene("room")


# ------------------------------------------------------------------ 6. a checkpoint's dataset options stay with it


def test_another_dataset_drops_the_checkpoints_dataset_options():
    stored = ["+head=unet", "dataset.num_train_scenes=16", "dataset.height=32", "train.steps=10"]
    merged = merge_overrides(stored, ["dataset=replica", "dataset.root=/r"])
    # the options replica has too (the image size) carry over like every other option of the checkpoint
    assert merged == ["+head=unet", "dataset.height=32", "train.steps=10", "dataset=replica", "dataset.root=/r"]
    assert foreign_dataset_note(stored, merged) == (
        "dataset=replica is not the checkpoint's dataset (embedded): its options dataset.num_train_scenes=16 are "
        "not options of replica and are not carried over")
    assert merge_overrides(stored, ["dataset=embedded"]) == [*stored, "dataset=embedded"]  # the same dataset keeps them
    assert foreign_dataset_note(stored, [*stored, "dataset=embedded"]) is None
    replica_stored = ["dataset=replica", "dataset.protocol=paper_parity"]
    assert merge_overrides(replica_stored, ["eval.splits=[train]"]) == [*replica_stored, "eval.splits=[train]"]
    # ``~key`` of a key the checkpoint set drops that override (Hydra could not delete a field of the new schema)
    assert merge_overrides(stored, ["~dataset.num_train_scenes"]) == ["+head=unet", "dataset.height=32",
                                                                       "train.steps=10"]


def test_finetune_of_an_embedded_checkpoint_on_replica_runs(embedded_checkpoint, replica_root):
    out = replica_root.parent / "finetuned"
    result = gpnerf("finetune", f"checkpoint={embedded_checkpoint}", "dataset=replica", f"dataset.root={replica_root}",
                    "dataset.scenes=[kitchen]", "dataset.unseen_scenes=[hall]", "dataset.height=32", "dataset.width=48",
                    "dataset.eval_step=2", "dataset.eval_count=2", "train.steps=1", "finetune.points=2",
                    "eval.save_images=0", f"out_dir={out}", cwd=replica_root.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    assert ("note: dataset=replica is not the checkpoint's dataset (embedded): its options "
            "dataset.num_train_scenes=1, dataset.num_unseen_scenes=1") in result.stderr
    assert (out / "metrics.json").is_file()
