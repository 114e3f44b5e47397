"""``render``: the MP4 / GIF / PNG frames of a trained model along a trajectory, and a bad path refused."""

import json
import os
import subprocess
import sys

import imageio.v2 as imageio

TINY = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.num_train_scenes=1", "feature_extractor.widths=[8,8,8,16]", "feature_extractor.fpn_channels=4",
    "field_aggregator.width=16", "field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
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
    bad = gpnerf("render", f"checkpoint={checkpoint}", "render.path=orbit", f"out_dir={tmp_path / 'bad'}")
    assert bad.returncode == 2 and bad.stderr.strip() == "error: render.path='orbit'; expected one of: interpolate, spiral"
    assert not (tmp_path / "bad").exists()
