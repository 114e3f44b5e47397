"""Checkpoint integrity (content hash), ``train.resume=auto`` and ``train.keep_checkpoints``."""

import struct
import zipfile

import pytest
import torch
from omegaconf import open_dict

from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.engine.resuming import plan_resume
from gpnerf_core.model.checkpoint import content_digest, read_checkpoint
from gpnerf_core.training.resume import newest_intact_checkpoint, run_checkpoints
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer


def tiny_cfg(tmp_path, *extra):
    return compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                    *extra])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A run folder with checkpoints at steps 1..4 of which train.keep_checkpoints=3 kept the newest three."""
    tmp_path = tmp_path_factory.mktemp("resume")
    cfg = tiny_cfg(tmp_path, "train.steps=4", "train.checkpoint_every=1", "train.keep_checkpoints=3",
                   f"out_dir={tmp_path / 'run'}")
    make_trainer(cfg, tmp_path / "run").fit(progress=False)
    return tmp_path, cfg


def flip_byte_inside_tensor(path, entry_suffix="data/0", offset=5):
    """Change one byte of a tensor's stored data in a torch zip file, leaving the archive readable."""
    with zipfile.ZipFile(path) as archive:
        info = next(i for i in archive.infolist() if i.filename.endswith(entry_suffix))
    with open(path, "r+b") as handle:
        handle.seek(info.header_offset + 26)
        name_length, extra_length = struct.unpack("<HH", handle.read(4))
        position = info.header_offset + 30 + name_length + extra_length + offset
        handle.seek(position)
        value = handle.read(1)[0]
        handle.seek(position)
        handle.write(bytes([value ^ 0x40]))


def test_keep_checkpoints_leaves_the_newest(trained):
    tmp_path, _ = trained
    assert [step for step, _ in run_checkpoints(tmp_path / "run")] == [2, 3, 4]


def test_a_checkpoint_carries_the_hash_of_its_contents(trained):
    tmp_path, _ = trained
    state = read_checkpoint(tmp_path / "run" / "checkpoints" / "step_0000004.pt")
    assert state["content_sha256"] == content_digest(state)
    reloaded = dict(state, step=state["step"] + 1)
    assert content_digest(reloaded) != state["content_sha256"]


def test_a_damaged_tensor_is_refused_and_auto_resume_takes_the_one_before(trained, tmp_path):
    source, _ = trained
    run = tmp_path / "copy"
    (run / "checkpoints").mkdir(parents=True)
    for step, path in run_checkpoints(source / "run"):
        (run / "checkpoints" / path.name).write_bytes(path.read_bytes())
    newest = run / "checkpoints" / "step_0000004.pt"
    flip_byte_inside_tensor(newest)
    torch.load(newest, weights_only=True)  # torch itself reads the damaged file without complaint
    with pytest.raises(DataError, match=r"step_0000004\.pt is damaged: its contents do not match"):
        read_checkpoint(newest)
    found, notes = newest_intact_checkpoint(run)
    assert found == run / "checkpoints" / "step_0000003.pt"
    assert len(notes) == 1 and "step_0000004.pt is damaged" in notes[0]
    for _, path in run_checkpoints(run)[:-1]:  # the newest is damaged already
        flip_byte_inside_tensor(path)
    with pytest.raises(DataError, match=r"none of the 3 checkpoints .* is intact"):
        newest_intact_checkpoint(run)
    assert len(run_checkpoints(run)) == 3  # nothing deleted


def test_auto_resume_picks_the_newest_and_records_its_path(trained):
    tmp_path, cfg = trained
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.train.resume = "auto"
        cfg.train.steps = 6
    plan = plan_resume(cfg, Distributed.single())
    assert plan.checkpoint == tmp_path / "run" / "checkpoints" / "step_0000004.pt" and plan.resuming
    assert cfg.train.resume == str(plan.checkpoint)
    assert any("resuming from" in note for note in plan.notes)


def test_auto_resume_in_an_empty_folder_starts_and_without_out_dir_is_refused(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.resume=auto", f"out_dir={tmp_path / 'new'}")
    plan = plan_resume(cfg, Distributed.single())
    assert plan.checkpoint is None and plan.replace_leftovers and cfg.train.resume is None
    with pytest.raises(ConfigError, match="train.resume=auto needs out_dir"):
        plan_resume(tiny_cfg(tmp_path, "train.resume=auto"), Distributed.single())
    finished = tmp_path / "finished"
    finished.mkdir()
    (finished / "metrics.json").write_text("{}")
    with pytest.raises(DataError, match="metrics.json but no checkpoint"):
        plan_resume(tiny_cfg(tmp_path, "train.resume=auto", f"out_dir={finished}"), Distributed.single())


@pytest.mark.parametrize("change, message", [
    ("seed=7", r"seed=7 differs from the checkpoint's seed=0"),
    ("train.steps=2", r"train.steps=2 is below the step 4 the checkpoint reached"),
])
def test_resuming_with_what_the_checkpoint_cannot_honour_is_refused(trained, change, message):
    tmp_path, _ = trained
    checkpoint = tmp_path / "run" / "checkpoints" / "step_0000004.pt"
    cfg = tiny_cfg(tmp_path, f"train.resume={checkpoint}", change)
    with pytest.raises(ConfigError, match=message):
        plan_resume(cfg, Distributed.single())
