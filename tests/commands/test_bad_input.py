"""Bad input through the real command line: one line on stderr, exit code 2, no traceback, no folder left behind."""

import os
import subprocess
import sys

import pytest

TINY = [
    "+head=unet", "+loss=dgs", "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1",
    "dataset.frames_per_scene=6", "dataset.eval_every=3", "dataset.height=32", "dataset.width=48",
    "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "train.steps=1", "eval.splits=[]", "threads=1",
]


def gpnerf(*args, cwd, env=None):
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", **(env or {}))
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_input")
    (root / "a_file").write_text("")
    return root


CASES = {
    "misspelled key": (["train.step=10"], "Could not override 'train.step'"),
    "wrong type": (["head.channels=abc"], "Value 'abc' of type 'str' could not be converted to Integer"),
    "float for a count": (["train.rays=1.5"], "could not be converted to Integer"),
    "negative rays": (["train.rays=-8"], "train.rays=-8: expected an integer >= 1"),
    "zero chunk": (["eval.chunk_rays=0"], "eval.chunk_rays=0: expected an integer >= 1"),
    "unknown key with +": (["+train.foo=1"], "unknown config key 'train.foo'"),
    "unknown head": (["+head=nope"], "unknown head 'nope'; known head names: instance, per_pixel, unet"),
    "unknown dataset": (["dataset=nope"], "unknown dataset 'nope'; known dataset names: capture, embedded, replica"),
    "unknown component option": (["+head.depth=3"], "head.depth is not an option of head 'unet'"),
    "source views": (["model.num_source_views=5"], "model.num_source_views=5 but scene 'layout_00' offers 3"),
    "bad device": (["device=tpu"], "device='tpu': expected auto, cpu or cuda[:N]"),
    "width the extractor cannot take": (["dataset.width=13"], "32x13: image size 32x13 (HxW) is not a multiple of 4"),
    "cuda without a GPU": (["device=cuda"], "device='cuda' but CUDA is not available"),
    "out_dir under a file": (["out_dir={ws}/a_file/run"], "cannot be created (Not a directory)"),
    "cache under a file": (["GPNERF_CACHE={ws}/a_file"], "cannot write the embedded scenes (Not a directory)"),
    "bad validation level": (["dataset.validate=fast"], "dataset.validate='fast': expected one of quick, full, off"),
    "missing init file": (["model.init={ws}/nope.pth"], "model.init={ws}/nope.pth: no such file"),
    "init file a folder": (["model.init={ws}"], "model.init={ws} is a folder; expected a file"),
    "resume missing": (["train.resume={ws}/nope.pt"], "train.resume={ws}/nope.pt: no such file"),
    "bad schedule": (["train.lr_schedule=linear"], "train.lr_schedule='linear': expected one of exponential, cosine"),
    "instance loss on a class head": (["loss=instance"], "loss 'instance' trains instances but head 'unet' predicts"),
    "weight average decay of 1": (["train.ema_decay=1"], "train.ema_decay=1.0: expected a decay in [0, 1)"),
    "a second loss with +": (["+loss=ce"], "+loss=ce: the config already selects a loss (an experiment's or a "
                                           "checkpoint's); replace it with loss=ce (without '+')"),
    "unknown weight choice": (["eval.weights=best"], "eval.weights='best': expected one of average, trained"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_and_exit_2(workspace, case):
    arguments, expected = CASES[case]
    arguments = [a.format(ws=workspace) for a in arguments]
    env = dict(a.split("=", 1) for a in arguments if a.startswith("GPNERF_"))
    overrides = [a for a in arguments if not a.startswith("GPNERF_")]
    out = workspace / f"run_{case.replace(' ', '_')}"
    if not any(o.startswith("out_dir=") for o in overrides):
        overrides.append(f"out_dir={out}")
    env.setdefault("GPNERF_CACHE", str(workspace / "cache"))
    result = gpnerf("run", *TINY, *overrides, cwd=workspace, env=env)
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.strip() and "pybullet build time" not in line]
    expected = expected.format(ws=workspace)
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert not out.exists()  # nothing half-written
    assert not (workspace / "outputs").exists()


def test_eval_without_checkpoint_and_with_a_foreign_file(workspace):
    result = gpnerf("eval", cwd=workspace)
    assert result.returncode == 2 and result.stderr.strip() == "error: eval needs checkpoint=<path to a .pt file written by run>"
    (workspace / "foreign.pt").write_bytes(b"not a checkpoint")
    result = gpnerf("eval", f"checkpoint={workspace / 'foreign.pt'}", cwd=workspace)
    assert result.returncode == 2 and "could not be read" in result.stderr and result.stderr.count("\n") == 1
