"""A trained model read back one way: ``load_trained`` reads and hashes a checkpoint once per file, whoever asks
(resuming, ``eval``'s launcher and task, ``model.init``), and configs written before a key moved read as today's."""

import shutil

import pytest
import torch
import yaml
from omegaconf import OmegaConf, open_dict

from gpnerf_core.config.compose import compose
from gpnerf_core.config.legacy import upgrade_config_yaml, upgrade_overrides
from gpnerf_core.engine.jobs import checkpoint_config, plan_resume
from gpnerf_core.errors import DataError
from gpnerf_core.model import checkpoint as checkpoint_module
from gpnerf_core.model.build import build_components
from gpnerf_core.model.trained import load_trained, release_trained
from gpnerf_core.model.weights import init_weights
from gpnerf_core.runtime.distributed import Distributed
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer
from training.test_resume import flip_byte_inside_tensor


def tiny_cfg(tmp_path, *extra):
    return compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                    *extra])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("trained")
    cfg = tiny_cfg(tmp_path, "train.steps=2", f"out_dir={tmp_path / 'run'}")
    make_trainer(cfg, tmp_path / "run").fit(progress=False)
    return tmp_path, tmp_path / "run" / "checkpoints" / "step_0000002.pt"


@pytest.fixture
def reads(monkeypatch):
    """Counts the checkpoint files read (``torch.load``) and content hashes computed."""
    counts = {"load": 0, "hash": 0}
    load, digest = torch.load, checkpoint_module.content_digest

    def counted_load(*args, **kwargs):
        counts["load"] += 1
        return load(*args, **kwargs)

    def counted_digest(*args, **kwargs):
        counts["hash"] += 1
        return digest(*args, **kwargs)

    monkeypatch.setattr(torch, "load", counted_load)
    monkeypatch.setattr(checkpoint_module, "content_digest", counted_digest)
    release_trained()
    yield counts
    release_trained()


def test_resuming_reads_and_hashes_the_checkpoint_once(trained, reads):
    tmp_path, checkpoint = trained
    cfg = tiny_cfg(tmp_path, "train.steps=3", f"train.resume={checkpoint}", f"out_dir={tmp_path / 'resumed'}")
    plan = plan_resume(cfg, Distributed.single())
    trainer = make_trainer(cfg, tmp_path / "resumed")
    assert plan.resuming and trainer.step == 2
    assert reads == {"load": 1, "hash": 1}


def test_evals_launcher_and_task_share_one_read(trained, reads):
    tmp_path, checkpoint = trained
    launched = load_trained(checkpoint)  # what launch_from_checkpoint reads for the overrides
    cfg = compose([*launched.overrides, f"checkpoint={checkpoint}"])
    again, notes = checkpoint_config(cfg, "eval")  # the task
    assert again is launched and cfg.model.coarse_samples == 6  # its settings restored (the run stored no overrides)
    assert reads == {"load": 1, "hash": 1}


def test_the_config_of_a_trained_model_is_rebuilt_one_way(trained):
    """``TrainedModel.config``: its overrides composed, its model settings kept where today's defaults differ."""
    tmp_path, checkpoint = trained
    written = load_trained(checkpoint)
    cfg = written.config(["eval.save_images=0"])
    assert cfg.eval.save_images == 0 and cfg.model.coarse_samples == 6 and cfg.model.name == "gnt"
    components = build_components(cfg, classes=written.classes)
    assert set(components.model.state_dict()) == set(written.weights()[0])


def test_model_init_refuses_a_damaged_gpnerf_checkpoint(trained, tmp_path):
    source, checkpoint = trained
    damaged = tmp_path / "damaged.pt"
    shutil.copy(checkpoint, damaged)
    flip_byte_inside_tensor(damaged)
    model = build_components(tiny_cfg(source)).model
    with pytest.raises(DataError, match=r"damaged\.pt is damaged: its contents do not match"):
        init_weights(model, damaged)
    report = init_weights(model, checkpoint)
    assert report.fmt == "gpnerf" and not report.missing and not report.unexpected


def test_a_config_written_before_models_were_families_reads_as_todays():
    old = yaml.safe_dump({"model": {"coarse_samples": 24, "semantic_field": {"enabled": True}},
                          "train": {"steps": 10, "fuse_rendered": False}})
    new = yaml.safe_load(upgrade_config_yaml(old))
    assert new["model"] == {"name": "gnt", "coarse_samples": 24, "semantic_field": {"enabled": True},
                            "fuse_rendered": False}
    assert new["train"] == {"steps": 10}
    assert upgrade_config_yaml(upgrade_config_yaml(old)) == upgrade_config_yaml(old)  # current configs pass unchanged
    assert upgrade_overrides(["+head=unet", "train.fuse_rendered=false", "++train.fuse_rendered=true"]) == [
        "+head=unet", "model.fuse_rendered=false", "++model.fuse_rendered=true"]


def test_an_old_checkpoint_evaluates_with_todays_keys(trained, tmp_path):
    """A checkpoint whose config predates the model families (no ``model.name``, ``train.fuse_rendered``) still
    restores: its config is read as today's and its overrides compose."""
    _, checkpoint = trained
    state = torch.load(checkpoint, weights_only=True)
    config = yaml.safe_load(state["config"])
    config["model"].pop("name")
    config["train"]["fuse_rendered"] = config["model"].pop("fuse_rendered")
    state["config"] = yaml.safe_dump(config, sort_keys=False)
    state["overrides"] = [*state["overrides"], "train.fuse_rendered=true"]
    state["content_sha256"] = checkpoint_module.content_digest(state)
    old = tmp_path / "old.pt"
    torch.save(state, old)
    release_trained()
    restored = load_trained(old)
    assert "model.fuse_rendered=true" in restored.overrides
    cfg = restored.config()
    with open_dict(cfg):
        cfg.checkpoint = str(old)
    assert OmegaConf.select(cfg, "model.fuse_rendered") is True and cfg.model.name == "gnt"
