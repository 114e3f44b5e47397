"""Ctrl-C and SIGTERM stop training cleanly: a checkpoint at the current step, the resume command, 130/143."""

import json
import os
import shlex
import signal
import subprocess
import sys
import time

import pytest

from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase

TINY = [
    "+head=unet", "+loss=dgs", "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1",
    "dataset.frames_per_scene=6", "dataset.eval_every=3", "dataset.height=32", "dataset.width=48",
    "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "train.log_every=1", "eval.splits=[unseen]", "eval.max_views_per_scene=1", "eval.save_images=0",
    "threads=1",
]


def environment(cache):
    return dict(os.environ, GPNERF_CACHE=str(cache), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", OMP_NUM_THREADS="1")


def start(out, cache, *extra):
    return subprocess.Popen(
        [sys.executable, "-m", "gpnerf_core", "run", *TINY, "train.steps=100000", f"out_dir={out}", *extra],
        env=environment(cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def wait_for_steps(out, steps, process, timeout=300):
    """Block until ``scalars.csv`` has logged ``steps`` steps (training is running)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        scalars = out / "scalars.csv"
        if scalars.exists() and scalars.read_text().count("train/loss") >= steps:
            return
        if process.poll() is not None:
            pytest.fail(f"training ended early: {process.communicate()[1][-2000:]}")
        time.sleep(0.2)
    process.kill()
    pytest.fail("training did not start in time")


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_writes_a_checkpoint_and_prints_the_resume_command(tmp_path, sig, code):
    out, cache = tmp_path / "run", tmp_path / "cache"
    process = start(out, cache)
    wait_for_steps(out, 2, process)
    process.send_signal(sig)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == code, stderr[-2000:]
    assert "Traceback" not in stderr
    line = next(line for line in stderr.splitlines() if line.startswith("interrupted ("))
    assert signal.Signals(sig).name in line
    checkpoints = sorted((out / "checkpoints").glob("step_*.pt"))
    assert checkpoints and str(checkpoints[-1]) in line
    assert not (out / ".gpnerf.lock").exists() and not (out / "metrics.json").exists()
    if sig == signal.SIGINT:
        resume_and_finish(line, checkpoints[-1], out, cache)
    else:
        auto_resume_and_finish(checkpoints[-1], out, cache)


def auto_resume_and_finish(checkpoint, out, cache):
    """The same command with ``train.resume=auto`` (what a restarted job runs) continues from the newest checkpoint."""
    step = int(checkpoint.stem.split("_")[1])
    result = subprocess.run([sys.executable, "-m", "gpnerf_core", "run", *TINY, f"train.steps={step + 1}",
                             f"out_dir={out}", "train.resume=auto"], env=environment(cache), capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"note: train.resume=auto: resuming from {checkpoint}" in result.stderr
    assert json.loads((out / "metrics.json").read_text())["train"]["steps"] == step + 1
    history = json.loads((out / "training_curves.json").read_text())
    assert [int(h["step"]) for h in history] == list(range(1, step + 2))


def resume_and_finish(line, checkpoint, out, cache):
    """Run the printed resume command (with a near step budget) in the same folder; it picks up where it stopped."""
    command = shlex.split(line.split("resume with: ", 1)[1])
    assert command[:4] == ["python", "-m", "gpnerf_core", "run"]
    assert f"out_dir={out}" in command and f"train.resume={checkpoint}" in command
    step = int(checkpoint.stem.split("_")[1])
    args = [a for a in command[4:] if not a.startswith("train.steps=")] + [f"train.steps={step + 2}"]
    result = subprocess.run([sys.executable, "-m", "gpnerf_core", "run", *args], env=environment(cache),
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train"]["steps"] == step + 2
    history = json.loads((out / "training_curves.json").read_text())
    assert [int(h["step"]) for h in history] == list(range(1, step + 3))


def test_a_signal_during_an_evaluation_between_steps_stops_at_once_with_the_step_it_followed(tmp_path):
    """An ``eval.every_steps`` evaluation can take minutes: SIGTERM inside it unwinds it, not after it and a step."""
    from gpnerf_core.config.compose import compose
    from gpnerf_core.training.interrupt import TrainingInterrupted
    from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer

    class SlowEvaluation:
        def __init__(self):
            self.finished = []

        def __call__(self, state):
            if state.steps_done == 2:
                os.kill(os.getpid(), signal.SIGTERM)  # arrives while "evaluating"
                time.sleep(5)
            self.finished.append(state.steps_done)

    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                   "train.steps=5"])
    trainer, evaluation = make_trainer(cfg, tmp_path / "run"), SlowEvaluation()
    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(TrainingInterrupted) as stopped:
        trainer.fit(progress=False, callbacks=[TrainingCallback(TrainingPhase.AFTER_STEP, evaluation, timed=False)])
    assert evaluation.finished == [1]  # step 2's evaluation was cut short, and no step ran after it
    assert stopped.value.signum == signal.SIGTERM and stopped.value.step == 2 and trainer.step == 2
    assert stopped.value.checkpoint.name == "step_0000002.pt" and stopped.value.checkpoint.exists()
    assert signal.getsignal(signal.SIGTERM) is handler
