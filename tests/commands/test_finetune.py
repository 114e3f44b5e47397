"""``finetune``: a generalized checkpoint trained further on chosen scenes, their held-out frames evaluated on a curve."""

import json

import pytest
import torch
from omegaconf import OmegaConf

from gpnerf_core.model.build import build_model
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation.curves import curve_points
from gpnerf_core.model.checkpoint import format_differences, model_differences
from gpnerf_core.model.weights import load_weights
from pipeline_check import TINY_CLI as TINY, gpnerf

def test_curve_points_run_from_zero_to_the_last_step():
    assert curve_points(6, 4) == [0, 2, 4, 6]
    assert curve_points(8, 4) == [0, 3, 5, 8]
    assert curve_points(2, 5) == [0, 1, 2]  # repeated step counts are evaluated once
    with pytest.raises(ConfigError, match="finetune.points=1: expected at least 2"):
        curve_points(10, 1)


def test_a_new_class_count_reinitialises_only_the_heads_last_layer():
    cfg = compose(["+head=unet", "+loss=dgs", *TINY])
    torch.manual_seed(0)
    old = build_model(cfg, num_classes=3)
    torch.manual_seed(1)
    new = build_model(cfg, num_classes=5)
    fresh = {k: v.clone() for k, v in new.state_dict().items()}
    reinitialised = load_weights(new, old.state_dict(), "finetune checkpoint=old.pt", new_classes=(3, 5))
    assert reinitialised and all(key.startswith("head.") for key in reinitialised)
    assert all(old.state_dict()[key].shape[0] == 3 for key in reinitialised)
    for key, value in new.state_dict().items():
        expected = fresh[key] if key in reinitialised else old.state_dict()[key]
        assert torch.equal(value, expected), key


def test_another_model_names_the_config_keys_that_differ():
    small = compose(["+head=unet", "+loss=dgs", *TINY])
    wide = compose(["+head=unet", "+loss=dgs", *TINY, "model.field_aggregator.width=32", "model.feature_extractor.fpn_channels=8"])
    with pytest.raises(ConfigError, match=r"finetune checkpoint=old.pt: tensor .* differs from the checkpoint's: .*"
                                          r"model.field_aggregator.width"):
        load_weights(build_model(wide, 3), build_model(small, 3).state_dict(), "finetune checkpoint=old.pt",
                     new_classes=(3, 3), explain=lambda: format_differences(
                         model_differences(OmegaConf.to_yaml(small), OmegaConf.to_yaml(wide))))


def test_finetune_on_an_unseen_scene_writes_the_curve(tmp_path):
    base = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, "train.steps=3", f"out_dir={tmp_path / 'base'}",
                  cwd=tmp_path)
    assert base.returncode == 0, base.stderr[-2000:]
    generalized = json.loads((tmp_path / "base" / "metrics.json").read_text())["eval"]["unseen"]
    checkpoint = tmp_path / "base" / "checkpoints" / "step_0000003.pt"
    tuned = gpnerf("finetune", f"checkpoint={checkpoint}", "dataset.scenes=[unseen_00]", "train.steps=4",
                   "finetune.points=3", f"out_dir={tmp_path / 'tuned'}", cwd=tmp_path)
    assert tuned.returncode == 0, tuned.stderr[-2000:]
    metrics = json.loads((tmp_path / "tuned" / "metrics.json").read_text())
    curve = metrics["finetune"]["curve"]
    assert [point["step"] for point in curve] == [0, 2, 4] and metrics["finetune"]["scenes"] == ["unseen_00"]
    # Step 0 is the generalized model on the same held-out frames of the same scene.
    assert curve[0]["miou/image_mean_present"] == generalized["miou/image_mean_present"]
    assert curve[0]["psnr/clamped"] == generalized["psnr/clamped"]
    assert curve[-1]["train_seconds"] > 0 and metrics["eval"]["train_heldout"]["count/images"] == 2
    assert "finetune step 4:" in tuned.stderr

    missing = gpnerf("finetune", f"checkpoint={checkpoint}", "train.steps=2", f"out_dir={tmp_path / 'nope'}",
                     cwd=tmp_path)
    assert missing.returncode == 2 and not (tmp_path / "nope").exists()
    assert missing.stderr.strip() == ("error: finetune needs dataset.scenes=[<scene>, ...]: the scenes to fine-tune "
                                      "on (their held-out frames are evaluated, never trained on)")


def test_a_checkpoint_older_than_an_option_takes_its_default_and_keeps_its_own_values():
    """A checkpoint written before an option existed is evaluated and resumed with the option's default (a new
    option's default is the old behaviour); a value it had is restored; an option it had that is gone is named."""
    from types import SimpleNamespace

    from gpnerf_core.model.trained import restore_model_settings

    cfg = compose(["+head=unet", "+loss=dgs", *TINY])
    old = OmegaConf.to_container(cfg, resolve=True)
    del old["model"]["sampler"]
    old["model"]["fine_samples"] = 3
    old["model"]["retired_option"] = 1
    old_yaml = OmegaConf.to_yaml(OmegaConf.create(old))
    assert [key for key, _, _ in model_differences(old_yaml, OmegaConf.to_yaml(cfg))] == [
        "model.fine_samples", "model.retired_option"]
    from gpnerf_core.model.checkpoint import model_sections

    notes = restore_model_settings(cfg, SimpleNamespace(config_yaml=old_yaml, model_sections=model_sections()),
                                   typed=[])
    assert cfg.model.fine_samples == 3 and cfg.model.sampler == "uniform"
    assert notes == ["kept the checkpoint's value of model.fine_samples (the defaults changed since it was written)",
                     "the checkpoint's model.retired_option is no option of this version (left out)"]
