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
from gpnerf_core.engine.opening import open_trained, restore_trained_settings
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


OLD_PART_OVERRIDES = ["model/feature_extractor=resunet_fpn", "model.feature_extractor.widths=[8,8,8,16]",
                      "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
                      "model.field_aggregator.num_blocks=2", "model.lr.head=0.002"]
"""TINY_MODEL's part options and a rate as today's keys (``old_layout`` writes them as a checkpoint before the moves
did)."""


def old_layout(state):
    """``state`` as a checkpoint written before the family owned its subtree: the parts at the top of its config, the
    rates in ``train.lr`` (with the groups other families had), in its overrides too, and its recorded model
    sections naming the parts."""
    config = yaml.safe_load(state["config"])
    for kind in ("feature_extractor", "field_aggregator", "ray_aggregator"):
        config[kind] = config["model"].pop(kind)
    config["train"]["lr"] = {**config["model"].pop("lr"), "field": 5e-4, "grid": 1e-2}
    state["config"] = yaml.safe_dump(config, sort_keys=False)
    state["overrides"] = [*state["overrides"], *(o.replace("model/", "").replace("model.lr", "train.lr")
                                                 .replace("model.feature", "feature").replace("model.field", "field")
                                                 for o in OLD_PART_OVERRIDES), "train.lr.grid=0.1"]
    state["model_sections"] = ["model", "feature_extractor", "field_aggregator", "ray_aggregator", "head", "loss"]
    state["content_sha256"] = checkpoint_module.content_digest(state)
    return state


def test_a_checkpoint_written_before_the_family_owned_its_subtree_reads_as_todays(trained, tmp_path):
    _, checkpoint = trained
    state = torch.load(checkpoint, weights_only=True)
    today = yaml.safe_load(state["config"])
    old = tmp_path / "old.pt"
    torch.save(old_layout(state), old)
    restored = load_trained(old)
    assert yaml.safe_load(restored.config_yaml) == today  # the parts and rates under the model again
    assert restored.model_sections == ("model", "head", "loss")
    assert all(o in restored.overrides for o in OLD_PART_OVERRIDES)
    assert not any("grid" in o for o in restored.overrides)  # a rate of a group gnt has not: dropped
    cfg = compose(restored.overrides)
    restore_trained_settings(cfg, restored, restored.overrides, "eval")
    assert cfg.model.field_aggregator.width == 16 and list(cfg.model.feature_extractor.widths) == [8, 8, 8, 16]
    assert cfg.model.lr.head == 0.002 and "feature_extractor" not in cfg and "lr" not in cfg.train


def test_an_old_config_keeps_only_the_parts_its_family_builds():
    old = yaml.safe_dump({"model": {"name": "semantic_nerf"}, "feature_extractor": {"name": "resunet_fpn"},
                          "field_aggregator": {"name": "gnt_view"}, "ray_aggregator": {"name": "gnt_ray"}})
    assert yaml.safe_load(upgrade_config_yaml(old)) == {"model": {"name": "semantic_nerf"}}
    old = yaml.safe_dump({"model": {"name": "mvsnerf"}, "feature_extractor": {"name": "mvsnet"},
                          "field_aggregator": {"name": "gnt_view", "width": 8}})
    assert yaml.safe_load(upgrade_config_yaml(old)) == {"model": {"name": "mvsnerf",
                                                                  "feature_extractor": {"name": "mvsnet"}}}
    assert upgrade_overrides(["feature_extractor=mvsnet", "+feature_extractor.x=1", "field_aggregator.width=8",
                              "model.num_planes=8"], "mvsnerf") == [
        "model/feature_extractor=mvsnet", "+model.feature_extractor.x=1", "model.num_planes=8"]


def test_an_old_config_s_rates_move_to_the_groups_its_family_has():
    """``train.lr`` beside a family's own ``model.lr``: the family's rate won then and wins now; a group the family
    has not (every family's config had all five) is dropped."""
    shared = {"feature_extractor": 1e-3, "transformer": 5e-4, "head": 1e-3, "field": 5e-4, "grid": 1e-2}
    old = yaml.safe_dump({"model": {"name": "mvsplat", "lr": {"mvsplat": 5e-4}}, "train": {"steps": 3, "lr": shared}})
    assert yaml.safe_load(upgrade_config_yaml(old)) == {
        "model": {"name": "mvsplat", "lr": {"feature_extractor": 1e-3, "head": 1e-3, "mvsplat": 5e-4}},
        "train": {"steps": 3}}
    old = yaml.safe_dump({"model": {"name": "semantic_nerf"}, "train": {"lr": shared}})
    assert yaml.safe_load(upgrade_config_yaml(old))["model"]["lr"] == {"field": 5e-4, "grid": 1e-2}
    assert upgrade_overrides(["train.lr.field=0.01", "train.lr.head=1", "train.lr_schedule=cosine"],
                             "semantic_nerf") == ["model.lr.field=0.01", "train.lr_schedule=cosine"]
