"""Run folders: nothing lost, nothing silent, no traceback (issue 31).

A refused command leaves every byte of a folder as it was; a failed one removes only what it created; a plugin's bug
is one line naming the component; a value Hydra cannot read, an interpolation that does not resolve and a checkpoint
given as an empty value or a folder are one line each.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from gpnerf_core import ComponentSpec
from gpnerf_core.commands.run import run_task
from gpnerf_core.config.compose import compose
from gpnerf_core.config.overrides import quoted_for_hydra
from gpnerf_core.engine.sweeps import record_sweep_failure
from gpnerf_core.engine.setup import compose_checked
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.model.trained import checked_checkpoint_path, load_trained
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.plugins import PluginInfo
from gpnerf_core.runtime.run_folder import RunFolder, make_folder, remove_made_folders
from gpnerf_plugins.heads.per_pixel import PerPixelHead

TINY = [
    "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.height=32", "dataset.width=48", "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4",
    "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "train.steps=1", "eval.splits=[]", "threads=1",
]
DGS = ["+head=unet", "+loss=dgs", *TINY]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    return tmp_path_factory.mktemp("scenes") / "embedded"


def tiny(scenes: Path, out: Path, *overrides: str, head: str = "unet", loss: str = "dgs"):
    return compose([f"+head={head}", f"+loss={loss}", *TINY, f"dataset.root={scenes}", f"out_dir={out}", *overrides])


def fingerprint(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder``: a file by its bytes' hash, a folder by its name."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(folder.rglob("*"))}


def refused(cfg, capsys) -> tuple[int, str]:
    """Run ``run``'s task in this process on ``cfg``, expecting it to stop: ``(exit code, stderr)``."""
    with pytest.raises(SystemExit) as stopped:
        run_task(cfg)
    return stopped.value.code, capsys.readouterr().err


@pytest.fixture(scope="module")
def finished(scenes, tmp_path_factory):
    """A finished 1-step ``+loss=dgs`` run folder, trained in this process."""
    out = tmp_path_factory.mktemp("finished") / "dgs"
    run_task(tiny(scenes, out))
    assert (out / "checkpoints" / "step_0000001.pt").is_file() and (out / "metrics.json").is_file()
    return out


# -- case 1: a refused resume touches nothing ------------------------------------------------------------------


@pytest.mark.parametrize("loss, overrides, message", [
    ("ce", ["train.resume=auto"], "another model or loss config (loss.name: 'dgs' -> 'ce'"),
    ("dgs", ["model.field_aggregator.num_blocks=1", "train.resume={checkpoint}"], "(model.field_aggregator.num_blocks: 2 -> 1)"),
    ("dgs", ["model.field_aggregator.num_blocks=1", "train.resume=auto", "train.resume_strict=false"], "does not match"),
    ("dgs", ["train.ema_decay=0.9", "train.resume=auto"], "the checkpoint kept no weight average"),
])
def test_a_refused_resume_leaves_every_byte_of_the_finished_run(finished, scenes, capsys, loss, overrides, message):
    before = fingerprint(finished)
    checkpoint = finished / "checkpoints" / "step_0000001.pt"
    overrides = [o.format(checkpoint=checkpoint) for o in overrides]
    code, err = refused(tiny(scenes, finished, "train.steps=2", *overrides, loss=loss), capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert fingerprint(finished) == before


# -- case 2: a refusal never removes a folder ------------------------------------------------------------------


def test_a_refused_rerun_into_a_crashed_runs_folder_removes_nothing(finished, scenes, tmp_path, capsys):
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    for name in ("config.yaml", "config.sha256", "overrides.yaml", "plugins.json"):
        (crashed / name).write_bytes((finished / name).read_bytes())
    (crashed / "scalars.csv").write_text("step,loss\n")
    before = fingerprint(crashed)
    code, err = refused(tiny(scenes, crashed), capsys)
    assert code == 2 and "is not empty (scalars.csv): it holds no checkpoint to resume from" in err
    assert fingerprint(crashed) == before


def test_a_failed_command_removes_only_the_run_files_it_wrote_and_the_folders_it_made(tmp_path):
    run = tmp_path / "made" / "run"
    make_folder(run)
    folder = RunFolder(run)
    with pytest.raises(RuntimeError), folder:
        folder.claim(resuming=False, overwrite=False)
        for name in ("config.yaml", "scalars.csv", "tensorboard/events.1"):
            (run / name).parent.mkdir(exist_ok=True)
            (run / name).write_text("new")
        (run / "nonfinite_batch.pt").write_text("a diagnostic an error names")
        raise RuntimeError("the run failed at step 0")
    assert sorted(p.name for p in run.iterdir()) == ["nonfinite_batch.pt"]
    remove_made_folders(run)
    assert run.exists()  # not empty: what is in it stays
    (run / "nonfinite_batch.pt").unlink()
    remove_made_folders(run)
    assert not (tmp_path / "made").exists()  # both levels were made by this command

    kept = tmp_path / "kept"  # not made by this command: a setup file of an earlier attempt, and a checkpoint
    (kept / "checkpoints").mkdir(parents=True)
    (kept / "config.yaml").write_text("earlier")
    with pytest.raises(RuntimeError), RunFolder(kept) as resumed:
        resumed.claim(resuming=True, overwrite=False)
        (kept / "checkpoints" / "step_0000003.pt").write_text("checkpoint")
        (kept / "scalars.csv").write_text("step\n3\n")
        raise RuntimeError("failed after its first checkpoint")
    assert sorted(p.name for p in kept.iterdir()) == ["checkpoints", "config.yaml", "scalars.csv"]  # it can resume
    remove_made_folders(kept)
    assert kept.is_dir()


# -- case 3: a refused sweep job writes nothing where it was refused; every failure counts ----------------------


def test_a_sweep_sharing_one_out_dir_writes_nothing_there_and_counts_both_jobs(tmp_path):
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", GPNERF_CACHE=str(tmp_path / "cache"))
    result = subprocess.run(
        [sys.executable, "-m", "gpnerf_core", "run", "-m", *DGS, "seed=0,1", f"out_dir={tmp_path / 'x'}",
         "hydra.sweep.dir=sweep"],  # relative, as Hydra's default: a job is still listed once
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2, result.stderr[-2000:]
    assert "error: 2 job(s) of the sweep failed" in result.stderr and "Traceback" not in result.stderr
    assert result.stderr.count(str(tmp_path / "sweep" / "0")) == 1
    assert not (tmp_path / "x").exists()
    for job in ("0", "1"):
        record = json.loads((tmp_path / "sweep" / job / "error.json").read_text())
        assert "every job of the sweep would write that one folder" in record["error"] and "run_folder" not in record


def test_a_failed_job_marks_no_folder_it_did_not_make(finished, scenes, tmp_path):
    import shutil

    other = shutil.copytree(finished, tmp_path / "other")  # a finished run this process neither made nor claimed
    before = fingerprint(other)
    assert record_sweep_failure(tiny(scenes, other), "boom")  # counted, but not written into a finished run
    assert fingerprint(other) == before
    new = tmp_path / "new"
    assert record_sweep_failure(tiny(scenes, new), "boom")
    assert json.loads((new / "error.json").read_text())["error"] == "boom" and (new / "config.yaml").is_file()


# -- case 4: a value Hydra's grammar cannot read ---------------------------------------------------------------


def test_a_value_with_an_equals_sign_is_quoted_and_arrives_as_typed(tmp_path):
    assert quoted_for_hydra("out_dir=a=b/run") == "out_dir='a=b/run'"
    assert quoted_for_hydra("out_dir=C:\\runs\\a") == "out_dir=C:\\runs\\a"  # Hydra reads it as it is
    assert quoted_for_hydra("out_dir=it's#1") == "out_dir='it\\'s#1'"
    assert quoted_for_hydra("seed=0,1") == "seed=0,1"  # a sweep stays a sweep
    for value in ("a=b/run", "it's#1", "x\\"):
        assert compose([quoted_for_hydra(f"out_dir={value}")]).out_dir == value
    with pytest.raises(ConfigError, match=r"^out_dir=a=b/run: Hydra's override grammar cannot read it \(.*\); put "
                                          r"the value in quotes, as one shell argument: \"out_dir='a=b/run'\"$"):
        compose_checked(["out_dir=a=b/run"])  # what is left when quoting cannot help
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", GPNERF_CACHE=str(tmp_path / "cache"))
    result = subprocess.run(
        [sys.executable, "-m", "gpnerf_core", "run", *DGS, f"out_dir={tmp_path / 'a=b' / 'run'}",
         f"train.resume={tmp_path / 'a=b' / 'nope.pt'}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: train.resume={tmp_path / 'a=b' / 'nope.pt'}: no such file; expected a " \
                                    ".pt file written by run (in <run>/checkpoints/)"
    assert not (tmp_path / "a=b").exists()  # made by precheck for the refused run, and removed again


# -- case 5: an interpolation that does not resolve ------------------------------------------------------------


def test_an_unresolvable_interpolation_is_one_line_naming_the_key():
    with pytest.raises(ConfigError) as refused_steps:
        compose_checked(["train.steps=${oops}"])
    assert str(refused_steps.value) == (
        "train.steps=${oops}: the interpolation cannot be resolved (Interpolation key 'oops' not found); ${...} must "
        "name a key of the config, e.g. ${train.rays}"
    )
    with pytest.raises(ConfigError, match=r"^eval.splits\[0\]=\$\{nope.x\}: the interpolation cannot be resolved"):
        compose_checked(["eval.splits=[${nope.x}]"])
    assert compose_checked(["train.steps=${train.rays}"]).train.steps == compose([]).train.rays


# -- case 6: a plugin head whose forward raises ----------------------------------------------------------------


@dataclass
class BrokenHeadConfig:
    name: str = "broken"


class BrokenHead(PerPixelHead):
    """A plugin head with a bug: decoding raises."""

    def __init__(self, in_dim: int, in_levels: int, num_outputs: int) -> None:
        super().__init__(in_dim, in_levels, num_outputs, hidden_dim=8, hidden_layers=0)

    def decode(self, features):
        raise RuntimeError("index 7 is out of bounds for dimension 0 with size 4")


@pytest.fixture
def broken_head(monkeypatch):
    """``+head=broken`` from the distribution ``gpnerf-broken-head 0.1``, registered in this process."""
    from hydra.core.config_store import ConfigStore

    registry = get_registry()
    plugin = PluginInfo("broken_head", "gpnerf-broken-head", "0.1")
    monkeypatch.setitem(registry.plugins, plugin.name, plugin)
    registry.add("head", ComponentSpec("broken", BrokenHead, BrokenHeadConfig, "raises in forward (tests)"), plugin)
    ConfigStore.instance().store(group="head", name="broken", node=BrokenHeadConfig, provider=plugin.name)
    yield
    registry.components["head"].pop("broken", None)


def test_a_head_that_raises_is_one_line_naming_it_and_leaves_nothing(broken_head, scenes, tmp_path, capsys,
                                                                       monkeypatch):
    out = tmp_path / "runs" / "broken"
    make_folder(out)  # as precheck does for the command line
    code, err = refused(tiny(scenes, out, head="broken"), capsys)
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 1 and "Traceback" not in err
    assert errors == ["error: head 'broken' (plugin broken_head, gpnerf-broken-head 0.1) raised RuntimeError: index 7 "
                      "is out of bounds for dimension 0 with size 4; a fault in that plugin's code: GPNERF_DEBUG=1 "
                      "shows the traceback to report to its authors"]
    assert not (tmp_path / "runs").exists()

    kept = tmp_path / "kept"  # a folder the user made: it stays, as empty as it was
    kept.mkdir()
    monkeypatch.setenv("GPNERF_DEBUG", "1")
    with pytest.raises(RuntimeError, match="index 7 is out of bounds"):
        run_task(tiny(scenes, kept, head="broken"))
    assert list(kept.iterdir()) == []


# -- case 7: a checkpoint given as an empty value or a folder --------------------------------------------------


def test_an_empty_or_folder_checkpoint_is_named_with_the_newest_checkpoint_in_it(tmp_path):
    with pytest.raises(DataError, match=r"^checkpoint= is empty; expected checkpoint=<path to a \.pt file"):
        load_trained("")
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for step in (2, 10):
        (run / "checkpoints" / f"step_{step:07d}.pt").write_bytes(b"")
    newest = run / "checkpoints" / "step_0000010.pt"
    for given in (run, run / "checkpoints"):
        with pytest.raises(DataError) as refused_folder:
            load_trained(given)
        assert str(refused_folder.value) == (
            f"checkpoint={given} is a folder; expected a .pt file (e.g. {newest}, the newest checkpoint in it)"
        )
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"^train.resume=.*empty is a folder, with no checkpoint in it; expected a "):
        checked_checkpoint_path(tmp_path / "empty", "train.resume")
