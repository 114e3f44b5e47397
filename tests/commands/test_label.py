"""``label``: a trained model's predicted labels of every frame of a capture, and the label-free path they open: a
per-scene Gaussian model fitted on a capture without labels, distilling them (``dataset.labels_from``); and what it
refuses (a model without classes, labels of another capture or size, a capture with neither sparse points nor depth)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from capture_fixtures import write_capture
from gpnerf_core.cli import main as cli_main
from gpnerf_plugins.datasets.embedded import SceneSetParams, generate
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes
from pipeline_check import TINY_CLI, in_process

SPLATS = ["model.init_points=300", "model.feature_dim=4", "model.sh_degree=1", "train.steps=2", "threads=1",
          "eval.save_images=0"]


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """A capture of an embedded layout without labels, a one-step GP-NeRF, and its labels of the capture."""
    work = tmp_path_factory.mktemp("label")
    root = generate(SceneSetParams(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=6, height=32, width=48,
                                   seed=0), work / "embedded")
    dataset = EmbeddedScenes(root=str(root), num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=6, height=32,
                             width=48, eval_every=3)
    capture = write_capture(dataset.load_scene(dataset.scenes("train")[0]), work / "room", labels=False)
    assert cli_main(["run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=1", f"out_dir={work / 'gpnerf'}"]) == 0
    checkpoint = next((work / "gpnerf" / "checkpoints").glob("*.pt"))
    capture_data = ["dataset=capture", f"dataset.root={capture}", "dataset.height=32", "dataset.width=48"]
    assert cli_main(["label", f"checkpoint={checkpoint}", *capture_data, f"out_dir={work / 'labels'}"]) == 0
    return work, capture, capture_data, checkpoint


def test_label_writes_every_frames_predicted_classes(labelled):
    work, _, _, checkpoint = labelled
    written = json.loads((work / "labels" / "labels.json").read_text())
    assert written["scene"] == "room" and written["frames"] == 6 and written["size"] == [32, 48]
    assert written["checkpoint"] == str(checkpoint) and written["source_views"] == 2 and len(written["classes"]) == 9
    images = sorted((work / "labels" / "labels").glob("*.png"))
    assert [p.name for p in images] == [f"{i:05d}.png" for i in range(6)]
    labels = np.asarray(Image.open(images[0]))
    assert labels.shape == (32, 48) and labels.dtype == np.uint8 and labels.max() < 9


def test_a_per_scene_gaussian_model_distils_the_labels_of_a_capture_without_labels(labelled):
    work, _, capture_data, _ = labelled
    out = work / "splats"
    assert cli_main(["run", "+experiment=baselines/semantic_3dgs", *capture_data,
                     f"dataset.labels_from={work / 'labels'}", *SPLATS, f"out_dir={out}"]) == 0
    scored = json.loads((out / "metrics.json").read_text())["eval"]["train_heldout"]
    assert 0.0 <= scored["miou/image_mean_present"] <= 1.0  # against the model's labels: what it distilled
    plain = work / "colour_only"  # without labels: colour and depth only, 3DGS itself
    assert cli_main(["run", "+experiment=baselines/semantic_3dgs", *capture_data, "loss.ce_weight=0", *SPLATS,
                     f"out_dir={plain}"]) == 0
    assert "miou/image_mean_present" not in json.loads((plain / "metrics.json").read_text())["eval"]["train_heldout"]


def test_labels_of_another_size_or_scene_and_a_capture_without_points_or_depth_are_refused(labelled, capsys):
    work, capture, capture_data, _ = labelled
    wrong = work / "wrong"
    wrong.mkdir()
    (wrong / "labels.json").write_text(json.dumps({"scene": "elsewhere", "frames": 6, "size": [32, 48],
                                                   "classes": ["a"], "ignore_index": 255}))
    other = in_process("run", "+experiment=baselines/semantic_3dgs", *capture_data, f"dataset.labels_from={wrong}",
                       *SPLATS, f"out_dir={work / 'refused'}")
    small = in_process("run", "+experiment=baselines/semantic_3dgs", "dataset=capture", f"dataset.root={capture}",
                       "dataset.height=16", "dataset.width=32", f"dataset.labels_from={work / 'labels'}", *SPLATS,
                       f"out_dir={work / 'refused'}")
    bare = write_capture(EmbeddedScenes(root=str(work / "embedded"), num_train_scenes=1, num_unseen_scenes=0,
                                        frames_per_scene=6, height=32, width=48, eval_every=3).load_scene("layout_00"),
                         work / "bare", labels=False, depth=False)
    nothing = in_process("run", "+experiment=baselines/semantic_3dgs", "dataset=capture", f"dataset.root={bare}",
                         "dataset.height=32", "dataset.width=48", "dataset.near=0.5", "dataset.far=8",
                         "loss.ce_weight=0", *SPLATS, f"out_dir={work / 'refused'}")
    err = capsys.readouterr().err
    assert other == 2 and "its labels are of scene 'elsewhere', which is no capture under" in err
    assert small == 2 and "labels of 6 frames at 32x48, capture 'room' has 6 frames loaded at 16x32" in err
    assert nothing == 2 and "scene 'bare' has no sparse points" in err and "and no depth in its training frames" in err
    assert not (work / "refused").exists()


def test_fit_from_a_checkpoint_on_a_capture_without_labels_takes_the_models_labels(labelled, tmp_path, monkeypatch,
                                                                                   capsys):
    work, _, capture_data, checkpoint = labelled
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    out = work / "fit"
    assert cli_main(["fit", f"checkpoint={checkpoint}", *capture_data, *SPLATS, "train.steps=1", "fit.eval_every=0",
                     f"out_dir={out}"]) == 0, capsys.readouterr().err[-2000:]
    err = capsys.readouterr().err
    assert "has no labels: model 'gnt''s labels of its 6 frames are the fit's targets" in err
    cached = next((tmp_path / "cache" / "labels").glob("room-*"))
    for name in [f"{i:05d}.png" for i in range(6)]:  # what `label` writes, frame by frame
        assert np.array_equal(np.asarray(Image.open(cached / "labels" / name)),
                              np.asarray(Image.open(work / "labels" / "labels" / name)))
    metrics = json.loads((out / "metrics.json").read_text())
    assert 0.0 <= metrics["eval"]["train_heldout"]["miou/image_mean_present"] <= 1.0  # scored against those labels
    assert f"labels_from: {cached}" in (out / "config.yaml").read_text()
    again = work / "fit_again"  # the next fit of the scene from the checkpoint reads the cache
    assert cli_main(["fit", f"checkpoint={checkpoint}", *capture_data, *SPLATS, "train.steps=1", "fit.eval_every=0",
                     f"out_dir={again}"]) == 0
    assert f"labels_from: {cached}" in (again / "config.yaml").read_text()
