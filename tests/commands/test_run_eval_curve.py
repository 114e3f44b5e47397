"""``eval.every_steps``: accuracy during training, with the training itself unchanged, and its chart."""

import json
import os
import subprocess
import sys

TINY = [
    "+head=unet", "+loss=dgs", "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6",
    "dataset.eval_every=3", "dataset.num_train_scenes=1", "model.feature_extractor.widths=[8,8,8,16]",
    "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2",
    "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2", "train.rays=16", "threads=1",
    "eval.save_images=1", "train.steps=4",
]


def gpnerf(*args, cwd):
    env = dict(os.environ, GPNERF_CACHE=str(cwd / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def test_evaluating_during_training_leaves_the_training_unchanged(tmp_path):
    plain = gpnerf("run", *TINY, "out_dir=plain", cwd=tmp_path)
    curved = gpnerf("run", *TINY, "eval.every_steps=2", "out_dir=curved", cwd=tmp_path)
    assert plain.returncode == 0 and curved.returncode == 0, curved.stderr[-2000:]
    assert "eval at step 2:" in curved.stderr
    a = json.loads((tmp_path / "plain" / "metrics.json").read_text())
    b = json.loads((tmp_path / "curved" / "metrics.json").read_text())
    assert a["eval"]["train_heldout"]["miou/image_mean_present"] == b["eval"]["train_heldout"]["miou/image_mean_present"]
    assert a["eval"]["unseen"]["psnr/clamped"] == b["eval"]["unseen"]["psnr/clamped"]
    assert a["train"]["final_loss"] == b["train"]["final_loss"]
    curve = b["eval_curve"]
    assert [entry["step"] for entry in curve] == [2, 4]
    assert curve[-1]["train_heldout"]["miou/image_mean_present"] == b["eval"]["train_heldout"]["miou/image_mean_present"]
    assert 0 < curve[0]["train_seconds"] < curve[1]["train_seconds"]
    assert "eval_curve" not in a
    assert sorted(p.name for p in (tmp_path / "curved" / "checkpoints").iterdir()) == [
        "step_0000002.pt", "step_0000004.pt"]
    chart = gpnerf("report", "curved", "--chart", "chart", cwd=tmp_path)
    assert chart.returncode == 0, chart.stderr
    assert (tmp_path / "chart" / "accuracy_vs_time.png").stat().st_size > 1000
