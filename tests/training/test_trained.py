"""A trained model read back one way: each command reads and hashes its checkpoint once, the read handed on
(resuming: ``plan_resume`` to the trainer; ``eval``: the launcher to the job; ``model.init``), nothing keeps it once its
weights are in the model, and configs written before a key moved read as today's."""

import gc
import shutil
import weakref

import pytest
import torch
import yaml
from omegaconf import OmegaConf

from gpnerf_core.config.compose import compose
from gpnerf_core.config.legacy import upgrade_config_yaml, upgrade_overrides
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.resuming import plan_resume
from gpnerf_core.errors import DataError
from gpnerf_core.model import checkpoint as checkpoint_module
from gpnerf_core.model.build import build_components
from gpnerf_core.model.trained import load_trained
from gpnerf_core.model.weights import init_weights
from gpnerf_core.runtime.distributed import Distributed
from pipeline_check import TINY_MODEL, TINY_SCENES, in_process, make_trainer
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
    yield counts


@pytest.mark.parametrize("resume", ["path", "auto"])
def test_resuming_reads_and_hashes_the_checkpoint_once_and_keeps_nothing(trained, reads, resume):
    tmp_path, checkpoint = trained
    folder = tmp_path / f"resumed_{resume}"
    if resume == "auto":  # the run's folder itself: the newest checkpoint in it
        shutil.copytree(checkpoint.parent, folder / "checkpoints")
    value = checkpoint if resume == "path" else "auto"
    cfg = tiny_cfg(tmp_path, "train.steps=3", f"train.resume={value}", f"out_dir={folder}")
    plan = plan_resume(cfg, Distributed.single())
    read = weakref.ref(plan.read)
    trainer = make_trainer(cfg, folder, resume_from=plan.take_read())
    assert plan.resuming and trainer.step == 2
    assert reads == {"load": 1, "hash": 1}
    gc.collect()
    assert read() is None and plan.read is None  # the checkpoint's tensors go once they are in the model


def test_evals_launcher_and_job_share_one_read(trained, reads, tmp_path):
    source, checkpoint = trained
    assert in_process("eval", f"checkpoint={checkpoint}", *TINY_SCENES, f"dataset.root={source / 'scenes'}",
                      "eval.save_images=0", "eval.max_views_per_scene=1", f"out_dir={tmp_path / 'eval'}") == 0
    assert reads == {"load": 1, "hash": 1}  # launch_from_checkpoint's read reached the job


def test_the_config_of_a_trained_model_is_rebuilt_one_way(trained):
    """``open_trained`` without Hydra: its overrides composed, its model settings kept where today's defaults differ
    (the run stored no overrides: every model setting comes from its config)."""
    tmp_path, checkpoint = trained
    written = load_trained(checkpoint)
    opened = open_trained(written, ["eval.save_images=0", *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"],
                          command="eval")
    cfg = opened.cfg
    assert cfg.eval.save_images == 0 and cfg.model.coarse_samples == 6 and cfg.model.name == "gnt"
    assert set(opened.components.model.state_dict()) == set(written.weights()[0])


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


def test_model_init_reads_its_file_once(trained, reads):
    source, checkpoint = trained
    init_weights(build_components(tiny_cfg(source)).model, checkpoint)
    assert reads == {"load": 1, "hash": 1}


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
    source, checkpoint = trained
    state = torch.load(checkpoint, weights_only=True)
    config = yaml.safe_load(state["config"])
    config["model"].pop("name")
    config["train"]["fuse_rendered"] = config["model"].pop("fuse_rendered")
    state["config"] = yaml.safe_dump(config, sort_keys=False)
    state["overrides"] = [*state["overrides"], "train.fuse_rendered=true"]
    state["content_sha256"] = checkpoint_module.content_digest(state)
    old = tmp_path / "old.pt"
    torch.save(state, old)
    restored = load_trained(old)
    assert "model.fuse_rendered=true" in restored.overrides
    cfg = open_trained(restored, [*TINY_SCENES, f"dataset.root={source / 'scenes'}"], command="eval").cfg
    assert OmegaConf.select(cfg, "model.fuse_rendered") is True and cfg.model.name == "gnt"
