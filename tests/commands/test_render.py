"""``render`` and ``export``: the MP4 / GIF / PNG frames of a trained model along a trajectory, its fused point
cloud, and bad values refused (the refusals through the command line: tests/commands/test_reliability_tools.py)."""

import json
import os
import subprocess
import sys
from types import SimpleNamespace

import imageio.v2 as imageio
import pytest
import trimesh

from gpnerf_core.commands.export import checked_min_views, exported_frames
from gpnerf_core.errors import ConfigError

TINY = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.num_train_scenes=1", "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4",
    "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "threads=1", "eval.save_images=0",
]


def test_render_writes_mp4_gif_and_frames(tmp_path):
    env = dict(os.environ, GPNERF_CACHE=str(tmp_path / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")

    def gpnerf(*args):
        return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=600)

    base = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, "train.steps=2", f"out_dir={tmp_path / 'base'}")
    assert base.returncode == 0, base.stderr[-2000:]
    checkpoint = tmp_path / "base" / "checkpoints" / "step_0000002.pt"
    result = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=4", f"out_dir={tmp_path / 'video'}")
    assert result.returncode == 0, result.stderr[-2000:]
    video = tmp_path / "video"
    assert sorted(p.name for p in (video / "frames").iterdir()) == [f"{i:04d}.png" for i in range(4)]
    frame = imageio.imread(video / "frames" / "0000.png")
    assert frame.shape[1] > 3 * 48  # rgb, depth and semantics side by side
    assert len(imageio.mimread(video / "trajectory.gif")) == 4
    assert sum(1 for _ in imageio.get_reader(video / "trajectory.mp4")) == 4  # len() of an ffmpeg reader is inf
    written = json.loads((video / "render.json").read_text())
    assert written["scene"] == "unseen_00"
    # consecutive poses reuse their sources' encoded features: fewer encoded than used
    reuse = written["feature_cache"]
    assert reuse["frames_reused"] > 0 and reuse["frames_encoded"] < 4 * 2
    assert not list(video.glob(".*partial*"))
    # export: the same checkpoint's points of the unseen scene's held-out frames, fused, as a PLY trimesh reads
    points = gpnerf("export", f"checkpoint={checkpoint}", "export.min_views=0", f"out_dir={tmp_path / 'points'}")
    assert points.returncode == 0, points.stderr[-2000:]
    exported = json.loads((tmp_path / "points" / "export.json").read_text())
    assert exported["scene"] == "unseen_00" and exported["frames"] == [1, 4] and exported["labels"] == "classes"
    cloud = trimesh.load(tmp_path / "points" / "points.ply")
    labels = cloud.metadata["_ply_raw"]["vertex"]["data"]["label"]
    assert len(cloud.vertices) == exported["points_written"] > 0 and 0 <= labels.min() and labels.max() < 9
    assert len(trimesh.load(tmp_path / "points" / "points_labels.ply").vertices) == len(cloud.vertices)
    assert not list((tmp_path / "points").glob(".*partial*"))
    stride = gpnerf("export", f"checkpoint={checkpoint}", "export.stride=3", f"out_dir={tmp_path / 'stride'}")
    assert stride.returncode == 2 and "error: export.stride=3: scene 'unseen_00' is 32x48" in stride.stderr
    assert not (tmp_path / "stride").exists()
    # each replaces its own finished folder with overwrite=true, as the refusal without it advises
    again = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=2", f"out_dir={video}")
    assert again.returncode == 2 and "replace it with overwrite=true" in again.stderr
    again = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=2", f"out_dir={video}", "overwrite=true")
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads((video / "render.json").read_text())["frames"] == 2 and len(list((video / "frames").iterdir())) == 2
    again = gpnerf("export", f"checkpoint={checkpoint}", "export.min_views=0", f"out_dir={tmp_path / 'points'}",
                   "overwrite=true")
    assert again.returncode == 0, again.stderr[-2000:]


def test_export_chooses_frames_and_refuses_what_cannot_be_exported():
    scene = SimpleNamespace(name="room", eval_frames=(1, 4, 7), train_frames=(0, 2, 3, 5, 6, 8), num_frames=9)
    assert exported_frames(scene, "eval", 1) == [1, 4, 7]
    assert exported_frames(scene, "train", 2) == [0, 3, 6]
    assert exported_frames(scene, "all", 4) == [0, 4, 8]
    with pytest.raises(ConfigError, match=r"^export.frames='some'; expected one of: eval, train, all$"):
        exported_frames(scene, "some", 1)
    with pytest.raises(ConfigError, match=r"^export.frames=eval: scene 'room' has no eval frames; choose train or all$"):
        exported_frames(SimpleNamespace(**{**scene.__dict__, "eval_frames": ()}), "eval", 1)
    assert checked_min_views(2, 3) == 2
    with pytest.raises(ConfigError, match=r"^export.min_views=3: only 3 frame\(s\) are exported"):
        checked_min_views(3, 3)
