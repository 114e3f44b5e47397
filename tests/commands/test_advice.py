"""Refusals that name the fix that works for the family and data at hand (issue 55, "Wrong or missing advice"): one
line, the real reason first, never a fix the family cannot take."""

from __future__ import annotations

import pytest

from capture_fixtures import write_capture
from gpnerf_plugins.datasets.embedded import SceneSetParams, generate
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes
from pipeline_check import in_process

SMALL = ["dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
         "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=0", "train.steps=1", "threads=1",
         "eval.save_images=0"]


def refusal(capsys, *argv: str) -> str:
    """The one error line a command that must be refused prints (exit code 2)."""
    assert in_process(*argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.fixture(scope="module")
def unlabelled_capture(tmp_path_factory):
    work = tmp_path_factory.mktemp("advice")
    root = generate(SceneSetParams(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=6, height=32, width=48,
                                   seed=0), work / "embedded")
    dataset = EmbeddedScenes(root=str(root), num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=6, height=32,
                             width=48, eval_every=3)
    return work, write_capture(dataset.load_scene("layout_00"), work / "room", labels=False)


def test_a_capture_without_labels_is_told_colour_only_or_labels_from_not_a_head(unlabelled_capture, capsys, tmp_path):
    _, capture = unlabelled_capture
    line = refusal(capsys, "run", "+experiment=baselines/semantic_3dgs", "dataset=capture", f"dataset.root={capture}",
                   "dataset.height=32", "dataset.width=48", "model.init_points=300", "train.steps=1", "threads=1",
                   f"out_dir={tmp_path / 'run'}")
    assert "dataset 'capture' has no labels" in line and "loss.ce_weight=0" in line
    assert "dataset.labels_from=" in line and "+head" not in line
    assert not (tmp_path / "run").exists()


def test_a_family_with_label_rendering_off_is_told_to_turn_it_on(capsys, tmp_path):
    line = refusal(capsys, "run", "+experiment=baselines/mvsplat", "model.label_rendering=false", *SMALL,
                   f"out_dir={tmp_path / 'run'}")
    assert "renders none as configured (model.label_rendering=false)" in line
    assert "model.label_rendering=true" in line and "loss.ce_weight=0" in line


def test_a_family_without_a_head_is_never_told_to_add_one(capsys, tmp_path):
    """The instance loss declares the scores it trains on its class, so the mismatch is the one refusal (before the
    loss set's own check of ``loss.ce_weight``, which the experiment set for its loss set)."""
    line = refusal(capsys, "run", "+experiment=baselines/semantic_nerf", "loss=instance", *SMALL,
                   f"out_dir={tmp_path / 'run'}")
    assert "loss 'instance' trains instances but model 'semantic_nerf' predicts classes and takes no head" in line
    assert "+head" not in line and "ce_weight" not in line


def test_a_family_that_takes_a_head_is_still_told_to_add_one(capsys, tmp_path):
    line = refusal(capsys, "run", "+loss=dgs", *SMALL, f"out_dir={tmp_path / 'run'}")
    assert "model 'gnt' renders none as configured" in line and "(+head=unet)" in line
    assert "train colour only (loss.ce_weight=0 loss.sd_weight=0 loss.dgs_weight=0)" in line


def test_depth_candidates_past_the_sane_range_are_refused_with_the_memory_they_would_need(capsys, tmp_path):
    """Was: a 40 GB allocator message from the first layer over the candidates."""
    line = refusal(capsys, "run", "+experiment=baselines/mvsplat", "model.depth_candidates=100000", *SMALL,
                   f"out_dir={tmp_path / 'run'}")
    assert line.startswith("error: model.depth_candidates=100000: expected 2 to 1024; ")
    assert "3.7e+11 weights, about 1.48e+03 GB in float32" in line
    assert not (tmp_path / "run").exists()


def test_a_family_that_trains_on_images_is_pointed_at_a_loss_set_on_images(capsys, tmp_path):
    line = refusal(capsys, "run", "+experiment=baselines/mvsplat", "loss=instance", *SMALL, f"out_dir={tmp_path / 'run'}")
    assert "loss 'instance' trains instances but model 'mvsplat' predicts classes" in line
    assert "(+head=instance)" in line and "(+loss=image)" in line and "dgs" not in line


def test_an_experiments_setting_for_a_part_an_override_replaced_is_named_with_the_fix():
    from gpnerf_core.engine.setup import compose_overrides
    from gpnerf_core.errors import ConfigError

    with pytest.raises(ConfigError) as refused:
        compose_overrides(["+experiment=baselines/semantic_3dgs", "loss=instance"])
    message = str(refused.value)
    assert "'experiment/baselines/semantic_3dgs' sets rgb_error" in message and "InstanceLossConfig" in message
    assert "keep the experiment's, or leave the experiment out" in message and "\n" not in message
