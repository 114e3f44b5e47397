"""The example third-party package installs offline, is listed with its version, trains, passes its own tests (which
use the contract kit) and uninstalls, leaving the environment as it was."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "gpnerf-head-separable"
DISTRIBUTION = "gpnerf-head-separable"
TINY = (  # a 4-step run on two 8-frame scenes of 48 x 64 pixels
    "dataset.num_train_scenes=1 dataset.num_unseen_scenes=1 dataset.frames_per_scene=8 dataset.eval_every=4 "
    "dataset.height=48 dataset.width=64 model.coarse_samples=8 model.fine_samples=4 model.num_source_views=2 "
    "train.steps=4 train.rays=32 eval.max_views_per_scene=1 eval.save_images=0 threads=1"
).split()


def child_env(cache):
    """The test environment with entry points enabled (the suite's conftest disables them)."""
    env = {k: v for k, v in os.environ.items() if k not in ("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "GPNERF_DISABLE_PLUGINS")}
    return dict(env, GPNERF_CACHE=str(cache), OMP_NUM_THREADS="1", PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")


def run(*args, cwd, env, timeout=300):
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def pip(*args, env):
    return run("-m", "pip", *args, cwd=EXAMPLE.parent, env=env, timeout=120)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    return tmp_path_factory.mktemp("example_plugin")


@pytest.fixture(scope="module")
def installed(workspace):
    """The example, copied (its build files stay out of the repository) and pip-installed without the network."""
    env = child_env(workspace / "cache")
    assert pip("show", DISTRIBUTION, env=env).returncode == 1, (
        f"{DISTRIBUTION} is already installed (left by a killed run?): python -m pip uninstall -y {DISTRIBUTION}")
    source = workspace / EXAMPLE.name
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    try:
        result = pip("install", "--no-index", "--no-deps", "--no-build-isolation", str(source), env=env)
        assert result.returncode == 0, result.stderr[-3000:]
        yield source, env
    finally:
        pip("uninstall", "-y", DISTRIBUTION, env=env)
        assert pip("show", DISTRIBUTION, env=env).returncode == 1, f"{DISTRIBUTION} is still installed"


def test_plugins_lists_the_example_with_its_version(installed):
    _, env = installed
    result = run("-m", "gpnerf_core", "plugins", cwd=EXAMPLE.parent, env=env)
    assert result.returncode == 0, result.stdout[-2000:]
    rows = {tuple(line.split()[:4]) for line in result.stdout.splitlines()}
    assert ("head", "separable", "gpnerf_head_separable", "0.1.0") in rows
    assert ("loss", "dice", "gpnerf_head_separable", "0.1.0") in rows


@pytest.mark.parametrize("loss", ["dgs", "dice"])
def test_a_tiny_run_trains_with_the_example_head(installed, workspace, loss):
    _, env = installed
    out = workspace / f"run_{loss}"
    result = run("-m", "gpnerf_core", "run", "+head=separable", f"+loss={loss}", "head.channels=16", *TINY,
                 f"out_dir={out}", cwd=workspace, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train"]["steps"] == 4
    for split in ("train_heldout", "unseen"):
        assert 0.0 <= metrics["eval"][split]["miou/image_mean_present"] <= 1.0
    head = next(c for c in json.loads((out / "plugins.json").read_text())["components"] if c["name"] == "separable")
    assert (head["provider"], head["version"]) == ("gpnerf_head_separable", "0.1.0")
    tags = {row["tag"] for row in csv.DictReader((out / "scalars.csv").open())}
    assert {"train/rgb", "train/ce", "train/sd", "train/dgs"} <= tags
    assert ("train/dice" in tags) == (loss == "dice")


def test_the_examples_own_tests_pass(installed):
    source, env = installed
    result = run("-m", "pytest", "-q", "-p", "no:cacheprovider", "tests", cwd=source, env=env)
    assert result.returncode == 0, result.stdout[-3000:]
    assert " passed" in result.stdout and "skipped" not in result.stdout
