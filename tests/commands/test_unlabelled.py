"""A trained model used on scenes without labels, through the command line: ``eval`` scores colour and depth and reports
every label metric as not available, ``render`` colours and names the checkpoint's classes on a dataset with no class
list, ``finetune +loss=label_free`` adapts the model without labels, and a loss set that needs labels is refused.

The scenes without labels are the embedded rooms behind the test plugin ``unlabelled_embedded``
(``tests/unlabelled_scenes.py``), installed as a distribution for the subprocesses.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gpnerf_core.commands import report
from gpnerf_core.config.overrides import merge_overrides
from gpnerf_plugins.datasets.embedded import CLASS_NAMES
from pipeline_check import TINY_CLI
from unlabelled_scenes import install

TESTS = Path(__file__).resolve().parents[1]
NO_CLASS_LIST = ["dataset=unlabelled_embedded", "dataset.class_list=false"]
REFUSAL = ("error: scene 'unseen_00' has no labels, but loss 'dgs' trains on labels; train without labels with "
           "+loss=label_free (colour + distillation from the 2D teacher)")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("unlabelled")
    install(root / "plugins")
    return root


def gpnerf(*args, cwd):
    """``python -m gpnerf_core <args>`` with the test plugin installed (entry points on) and its own scene cache."""
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    env["PYTHONPATH"] = os.pathsep.join([str(cwd / "plugins"), str(TESTS), env.get("PYTHONPATH", "")])
    env["GPNERF_CACHE"] = str(cwd / "cache")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def checkpoint(workspace):
    """A model trained 2 steps on the labelled embedded rooms."""
    base = gpnerf("run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=2", f"out_dir={workspace / 'base'}",
                  cwd=workspace)
    assert base.returncode == 0, base.stderr[-2000:]
    return workspace / "base" / "checkpoints" / "step_0000002.pt"


def test_eval_without_labels_scores_colour_and_reports_labels_as_not_available(workspace, checkpoint, tmp_path):
    out = workspace / "eval"
    result = gpnerf("eval", f"checkpoint={checkpoint}", *NO_CLASS_LIST, "eval.max_views_per_scene=1",
                    f"out_dir={out}", cwd=workspace)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (f"note: dataset 'unlabelled_embedded' has no class list: using the {len(CLASS_NAMES)} classes of "
            f"checkpoint {checkpoint} ({', '.join(CLASS_NAMES[:6])}, ...") in result.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    for split, scene in (("train_heldout", "layout_00"), ("unseen", "unseen_00")):
        values = metrics["eval"][split]
        assert math.isfinite(values["psnr/clamped"]) and math.isfinite(values["ssim/gaussian11"])
        assert math.isfinite(values["depth/abs_rel"]) and values["count/images"] == 1
        assert values["miou/image_mean_present"] is None and values["acc/total"] is None  # null, never 0.0
        assert values["labels/unavailable_reason"] == f"scene {scene!r} has no labels"
        assert f"{split}: labels: not available (scene {scene!r} has no labels) | PSNR " in result.stdout
    # report reads the nulls: a table cell 'n/a' and a chart of what was measured
    assert report.main([str(out), "--chart", str(tmp_path / "chart")]) == 0
    assert (tmp_path / "chart" / "speed_accuracy.png").is_file()


def test_render_without_a_class_list_uses_the_checkpoints_classes(workspace, checkpoint):
    out = workspace / "video"
    result = gpnerf("render", f"checkpoint={checkpoint}", *NO_CLASS_LIST, "render.frames=2", f"out_dir={out}",
                    cwd=workspace)
    assert result.returncode == 0, result.stderr[-2000:]
    rendered = json.loads((out / "render.json").read_text())
    assert rendered["classes"] == list(CLASS_NAMES) and rendered["classes_from"] == f"checkpoint {checkpoint}"
    assert "legend.png" in rendered["outputs"] and (out / "legend.png").is_file()
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["0000.png", "0001.png"]


def test_finetune_label_free_adapts_without_labels_and_keeps_the_classes(workspace, checkpoint):
    out = workspace / "tuned"
    result = gpnerf("finetune", f"checkpoint={checkpoint}", *NO_CLASS_LIST, "dataset.scenes=[unseen_00]",
                    "+loss=label_free", "train.steps=2", "finetune.points=2", f"out_dir={out}", cwd=workspace)
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    curve = metrics["finetune"]["curve"]
    assert [point["step"] for point in curve] == [0, 2] and metrics["finetune"]["reinitialised"] == []
    for point in curve:  # the held-out PSNR curve; the label metrics are null at every point
        assert math.isfinite(point["psnr/clamped"]) and point["miou/image_mean_present"] is None
    assert metrics["eval"]["train_heldout"]["labels/unavailable_reason"] == "scene 'unseen_00' has no labels"
    assert set(metrics["train"]) >= {"steps", "final_loss"} and math.isfinite(metrics["train"]["final_loss"])
    tuned = torch.load(out / "checkpoints" / "step_0000002.pt", map_location="cpu", weights_only=True)
    assert tuned["class_names"] == list(CLASS_NAMES)  # the adapted model keeps naming the checkpoint's classes
    assert "label_free" in (out / "config.yaml").read_text()


def test_finetune_with_a_loss_set_that_needs_labels_is_refused_before_any_work(workspace, checkpoint):
    out = workspace / "refused"
    result = gpnerf("finetune", f"checkpoint={checkpoint}", "dataset=unlabelled_embedded", "dataset.scenes=[unseen_00]",
                    "train.steps=2", f"out_dir={out}", cwd=workspace)
    assert result.returncode == 2 and result.stderr.strip() == REFUSAL
    assert not out.exists()


def test_the_checkpoints_loss_set_is_replaced_with_or_without_plus():
    stored = ["+head=unet", "+loss=dgs", "train.steps=600"]
    assert merge_overrides(stored, ["+loss=label_free"]) == ["+head=unet", "train.steps=600", "+loss=label_free"]
    assert merge_overrides(stored, ["loss=label_free"]) == ["+head=unet", "train.steps=600", "+loss=label_free"]
