"""Pose sanity (gpnerf_core.geometry.pose_sanity) on synthetic rigs, on the embedded scenes' real cameras, and where it is
reported: ``dataset.validate`` (refusals and notes) and ``data check``."""

from __future__ import annotations

import math
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from gpnerf_core.data.checks import pose_warnings
from gpnerf_core.interfaces.model import Capabilities
from gpnerf_core.errors import DataError
from gpnerf_core.geometry.pose_sanity import ISOLATED, LOOKING_AWAY, OUTLIER, SCALE, check_poses
from gpnerf_core.engine.validation import check_data
from gpnerf_plugins.datasets import tools
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes
from gpnerf_plugins.datasets.replica.dataset import ReplicaScenes

H, W = 48, 64
NEAR, FAR = 0.2, 6.5
FOCAL = W / (2 * math.tan(math.radians(35)))  # 70 degrees horizontally
COLOUR_ONLY = SimpleNamespace(semantic_output=None, capabilities=Capabilities(),
                              check_image_size=lambda height, width: None)
"""What ``check_data`` reads of a model that renders colour and depth only."""
K = torch.tensor([[FOCAL, 0.0, (W - 1) / 2], [0.0, FOCAL, (H - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, torch.linalg.cross(forward, right), forward, eye
    return c2w


def ring(count: int = 12, radius: float = 1.3) -> torch.Tensor:
    """``count`` cameras on a wavy circle at about 1 m height, all looking at a point 0.5 m above its centre."""
    return torch.stack([
        look_at((radius * math.cos(a), radius * math.sin(a), 1.0 + 0.1 * math.sin(3 * a)), (0.0, 0.0, 0.5))
        for a in (2 * math.pi * k / count for k in range(count))
    ])


def check(c2w: torch.Tensor, near=NEAR, far=FAR, **kwargs):
    return check_poses(c2w, K.expand(len(c2w), 3, 3), H, W, near, far, **kwargs)


def flagged(findings) -> set[tuple[str | None, str]]:
    return {(f.frame, f.kind) for f in findings}


@pytest.mark.parametrize("count", [6, 12, 36])
def test_a_clean_ring_has_no_finding(count):
    assert check(ring(count)) == []


def test_a_forward_walk_and_a_tight_cluster_have_no_finding():
    walk = torch.stack([look_at((0.1 * k, 0.0, 1.5), (0.1 * k + 3.0, 0.3 * math.sin(k / 10), 1.4)) for k in range(120)])
    assert check(walk) == []  # 12 m long: its far end is a chain of close cameras, not an outlier
    jitter = torch.randn(20, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.003
    cluster = torch.stack([look_at(tuple((j + torch.tensor([0.0, 0.0, 1.0])).tolist()), (2.0, 0.0, 1.0)) for j in jitter])
    assert check(cluster) == []  # millimetres of jitter around one spot: the floor keeps it from being outliers


def test_a_camera_moved_100x_away_is_an_outlier():
    c2w = ring()
    c2w[3, :3, 3] *= 100
    findings = check(c2w, names=[f"img_{i:03d}.png" for i in range(12)])
    assert ("img_003.png", OUTLIER) in flagged(findings)
    assert {frame for frame, _ in flagged(findings)} == {"img_003.png"}
    outlier = next(f for f in findings if f.kind == OUTLIER)
    assert not outlier.refuses and "median camera centre" in outlier.message and "x 1.4826 x MAD" in outlier.message
    assert str(outlier).startswith("frame img_003.png: outlier camera: its centre is 160 m")  # 100 x 1.3 m + the rest


def test_a_turned_camera_looks_away():
    c2w = ring()
    c2w[5, :3, :3] = c2w[5, :3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    findings = check(c2w)
    assert flagged(findings) == {("5", LOOKING_AWAY)} and not findings[0].refuses


def test_a_far_camera_with_no_overlap_is_isolated():
    c2w = torch.cat([ring(), look_at((50.0, 0.0, 1.0), (60.0, 0.0, 1.0))[None]])
    findings = check(c2w)
    assert ("12", ISOLATED) in flagged(findings) and {frame for frame, _ in flagged(findings)} == {"12"}


def test_a_camera_in_the_rig_looking_where_no_other_does_is_isolated_but_no_outlier():
    up = look_at((0.0, 0.0, 1.5), (0.0, 0.01, 5.0), up=(0.0, 1.0, 0.0))  # at the centre, looking at the ceiling
    findings = check(torch.cat([ring(), up[None]]), far=2.0)
    assert flagged(findings) == {("12", ISOLATED), ("12", LOOKING_AWAY)}


@pytest.mark.parametrize("factor, rule", [(1000.0, "more than far"), (1e-4, "no parallax")])
def test_a_rescaled_rig_refuses_and_its_suggested_scale_fixes_it(factor, rule):
    c2w = ring()
    c2w[:, :3, 3] *= factor
    [finding] = check(c2w)
    assert finding.kind == SCALE and finding.frame is None and finding.refuses and rule in finding.message
    assert 0.5 < finding.factor * factor < 2.0  # brings the rig back to about metres
    assert f"dataset.scale={finding.message.split('dataset.scale=')[1].split()[0]}" in finding.message
    c2w[:, :3, 3] *= finding.factor
    assert check(c2w) == []


def test_content_beyond_far_is_a_scale_warning():
    [finding] = check(ring(36), far=3.0, depths=torch.full((36,), 20.0, dtype=torch.float64))
    assert finding.kind == SCALE and not finding.refuses and "the frames' depths put the content about 20 m" in finding.message
    c2w = ring(36)
    c2w[:, :3, 3] *= 10  # axes meet 14 m ahead, neighbours 2.3 m apart: under far, so a warning only
    [finding] = check(c2w, far=3.0)
    assert finding.kind == SCALE and not finding.refuses and "optical axes meet about 14 m" in finding.message


def test_per_frame_bounds_and_depths_and_bad_input():
    c2w = ring()
    near, far = torch.full((12,), NEAR), torch.full((12,), FAR)
    distances = (c2w[:, :3, 3] - torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)).norm(dim=-1)
    assert check(c2w, near=near, far=far, depths=distances) == []
    assert check(c2w[:1]) == []  # nothing to compare a single camera with
    with pytest.raises(DataError, match="frame 3: near 7, far 6.5; expected 0 < near < far"):
        check(c2w, near=torch.where(torch.arange(12) == 3, 7.0, NEAR))
    c2w[4, 0, 3] = math.nan
    with pytest.raises(DataError, match="frame cam4: camera pose is not finite"):
        check(c2w, names=[f"cam{i}" for i in range(12)])


def test_hundreds_of_frames_stay_fast():
    import time

    c2w = ring(300)
    start = time.perf_counter()
    assert check(c2w) == []
    assert time.perf_counter() - start < 5.0  # about 0.05 s alone on one core


# ----------------------------------------------------------------------------------- the embedded scenes and the checks


@pytest.fixture(scope="module")
def embedded(tmp_path_factory) -> EmbeddedScenes:
    """The main job's embedded scenes (4 + 1 layouts, 36 frames, seed 0: the same cameras) at 16 x 24 pixels."""
    dataset = EmbeddedScenes(root=str(tmp_path_factory.mktemp("embedded")), height=16, width=24)
    dataset.prepare()
    return dataset


def test_the_embedded_scenes_real_cameras_pass(embedded):
    scenes = embedded.scenes("train") + embedded.scenes("unseen")
    assert len(scenes) == 5
    for name in scenes:
        scene = embedded.load_scene(name)
        assert check_poses(scene.c2w, scene.intrinsics, scene.height, scene.width, scene.near, scene.far) == []
    assert embedded.check_files(scenes, "quick") == [] and pose_warnings(embedded, scenes, "quick") == []


@pytest.fixture
def damaged(embedded, tmp_path):
    """A copy of the embedded set read as a Replica layout: layout_00 frame 2 moved 100x away, layout_01 x 1000."""
    root = tmp_path / "replica"
    shutil.copytree(embedded.prepare(), root, ignore=shutil.ignore_patterns("layout_02", "layout_03"))
    for scene, edit in (("layout_00", lambda p: p[2, :3, 3].__imul__(100)), ("layout_01", lambda p: p[:, :3, 3].__imul__(1000))):
        path = root / scene / "Sequence_1" / "traj_w_c.txt"
        poses = np.loadtxt(path).reshape(-1, 4, 4)
        edit(poses)
        np.savetxt(path, poses.reshape(-1, 16))
    return root


def _replica(root, scenes):
    return ReplicaScenes(root=str(root), scenes=scenes, unseen_scenes=["unseen_00"], height=16, width=24)


def test_validate_refuses_a_scale_and_notes_an_outlier(damaged, capsys):
    both = ["layout_00/Sequence_1", "layout_01/Sequence_1"]
    dataset = _replica(damaged, ["layout_00", "layout_01"])
    [problem] = dataset.check_files(both, "quick")
    assert problem.startswith("scene 'layout_01/Sequence_1': implausible scale: neighbouring cameras are a median")
    assert "dataset.scale=0.0" in problem
    [note, *others] = pose_warnings(dataset, both, "quick")
    assert note.startswith("scene 'layout_00/Sequence_1' frame 2: outlier camera:")
    assert all(line.startswith("scene 'layout_00/Sequence_1' frame 2: ") for line in others)
    assert pose_warnings(dataset, both, "off") == []

    cfg = OmegaConf.create({"eval": {"splits": ["train", "unseen"]}, "model": {"num_source_views": 2}})
    clean = _replica(damaged, ["layout_00"])  # only the warning: training goes on, the note is on stderr
    check_data(cfg, SimpleNamespace(dataset=clean, loss=None, model=COLOUR_ONLY))
    assert "note: scene 'layout_00/Sequence_1' frame 2: outlier camera:" in capsys.readouterr().err
    with pytest.raises(DataError, match=r"found 1 problem\(s\) before training; first: scene 'layout_01/Sequence_1': impl"):
        check_data(cfg, SimpleNamespace(dataset=dataset, loss=None, model=COLOUR_ONLY))


def test_data_check_prints_the_findings_with_frame_names(damaged, capsys):
    assert tools.check([str(damaged), "--layout", "replica"]) == 1
    out = capsys.readouterr().out
    assert f"note: {damaged}/layout_00/Sequence_1/traj_w_c.txt: pose: frame 2: outlier camera:" in out
    assert (f"{damaged}/layout_01/Sequence_1/traj_w_c.txt: expected cameras whose scale fits near = 0.1 m, far = 10 m "
            "(--near/--far), found implausible scale:") in out
    assert "unseen_00" not in "".join(line for line in out.splitlines() if "pose:" in line or "scale" in line)
    assert tools.check([str(damaged), "--layout", "replica", "--far", "5000"]) == 0  # in those units it fits
