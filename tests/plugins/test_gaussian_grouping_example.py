"""The Gaussian Grouping example package (``examples/gpnerf-gaussian-grouping``): a third-party per-scene Gaussian
family installs offline, is listed with its version, trains from its own preset (``+experiment=gaussian_grouping``,
shipped through ``gpnerf_config_searchpaths``), logs its own loss terms, and its checkpoint goes through ``eval``,
``render``, ``export`` (each Gaussian's slot) and the viewer's splats; its own tests (the contract kit and its broken
variants) pass; it uninstalls, leaving the environment as it was."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ply_reader import read_ply

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "gpnerf-gaussian-grouping"
DISTRIBUTION = "gpnerf-gaussian-grouping"
SCENES = ["dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6",
          "dataset.eval_every=3", "dataset.height=32", "dataset.width=48", "dataset.scenes=[layout_00]"]
TINY = [*SCENES, "model.init_points=300", "model.identity_dim=4", "model.sh_degree=1", "model.reg3d_every=2",
        "model.reg3d_sample_size=50", "train.steps=4", "train.log_every=1", "eval.save_images=0", "threads=1"]
CHECKPOINT = "checkpoints/step_0000004.pt"


def child_env(cache):
    """The test environment with entry points enabled (the suite's conftest disables them)."""
    env = {k: v for k, v in os.environ.items() if k not in ("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "GPNERF_DISABLE_PLUGINS")}
    return dict(env, GPNERF_CACHE=str(cache), OMP_NUM_THREADS="1", PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")


def run(*args, cwd, env, timeout=300):
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    workspace = tmp_path_factory.mktemp("gaussian_grouping")
    env = child_env(workspace / "cache")
    pip = lambda *args: run("-m", "pip", *args, cwd=workspace, env=env, timeout=120)  # noqa: E731
    assert pip("show", DISTRIBUTION).returncode == 1, (
        f"{DISTRIBUTION} is already installed (left by a killed run?): python -m pip uninstall -y {DISTRIBUTION}")
    source = workspace / EXAMPLE.name
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    try:
        result = pip("install", "--no-index", "--no-deps", "--no-build-isolation", str(source))
        assert result.returncode == 0, result.stderr[-3000:]
        yield workspace, source, env
    finally:
        pip("uninstall", "-y", DISTRIBUTION)
        assert pip("show", DISTRIBUTION).returncode == 1, f"{DISTRIBUTION} is still installed"


@pytest.fixture(scope="module")
def trained(installed):
    workspace, _, env = installed
    out = workspace / "run"
    result = run("-m", "gpnerf_core", "run", "+experiment=gaussian_grouping", *TINY, f"out_dir={out}", cwd=workspace,
                 env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def test_plugins_lists_the_family_with_its_version(installed):
    workspace, _, env = installed
    result = run("-m", "gpnerf_core", "plugins", cwd=workspace, env=env)
    assert result.returncode == 0, result.stdout[-2000:]
    rows = {tuple(line.split()[:4]) for line in result.stdout.splitlines()}
    assert ("model", "gaussian_grouping", "gpnerf_gaussian_grouping", "0.1.0") in rows


def test_it_trains_from_its_preset_with_its_own_terms_and_is_scored_as_instances(trained):
    metrics = json.loads((trained / "metrics.json").read_text())
    assert metrics["train"]["steps"] == 4
    assert 0.0 <= metrics["eval"]["train_heldout"]["instance/ap_matched@0.75"] <= 1.0
    tags = {row["tag"] for row in csv.DictReader((trained / "scalars.csv").open())}
    assert {"train/rgb", "train/ssim", "train/identity", "train/identity_3d"} <= tags
    assert "train/ce" not in tags


def test_its_checkpoint_goes_through_eval_render_and_export_with_its_slots(installed, trained):
    workspace, _, env = installed
    checkpoint = f"checkpoint={trained / CHECKPOINT}"
    for command in ("eval", "render", "export"):
        result = run("-m", "gpnerf_core", command, checkpoint, *SCENES, "threads=1", f"out_dir={workspace / command}",
                     cwd=workspace, env=env)
        assert result.returncode == 0, f"{command}: {result.stderr[-3000:]}"
    labels = np.asarray(read_ply((workspace / "export" / "gaussians.ply").read_bytes())["label"])
    assert labels.size > 0 and ((labels >= -1) & (labels < 16)).all()


def test_report_names_it_and_stress_runs_it(installed, trained):
    workspace, _, env = installed
    report = run("-m", "gpnerf_core", "report", str(trained), cwd=workspace, env=env)
    assert report.returncode == 0, report.stderr[-3000:]
    assert "| gaussian_grouping | - | image |" in report.stdout
    stress = run("-m", "gpnerf_core", "stress", str(trained), "--quick", "--cases", "rotation_noise", "--threads", "1",
                 "--out", str(workspace / "stress"), cwd=workspace, env=env)
    assert stress.returncode == 0, stress.stderr[-3000:]
    written = (workspace / "stress" / "stress.md").read_text()
    assert "Gaussian Grouping (image)" in written  # the method by the name its spec declares
    assert "model 'gaussian_grouping' renders from its own parameters (per-scene)" in written  # sources it has none of


def test_the_viewer_draws_its_gaussians(installed, trained):
    workspace, _, env = installed
    script = f"""
import torch
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.model.trained import load_trained
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.tools.viewer.renderer import SceneRenderer
from gpnerf_core.tools.viewer.splats import splat_arrays

components = open_trained(load_trained({str(trained / CHECKPOINT)!r}), {SCENES!r}, command="view",
                          weights="trained", device=torch.device("cpu")).components
renderer = SceneRenderer(components.model.eval(), FrameCache(components.dataset, torch.device("cpu")),
                         components.view_selector, num_classes=components.classes.num_classes, chunk_rays=256,
                         default_source_views=0, feature_cache=SourceFeatureCache(16))
splats = renderer.gaussians("layout_00", ())
assert renderer.draws_gaussians and splats.count == components.model.gaussians.size
print("splats", splat_arrays(splats, "class", renderer.label_count)["centers"].shape[0])
"""
    result = run("-c", script, cwd=workspace, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "splats" in result.stdout


def test_the_examples_own_tests_pass(installed):
    _, source, env = installed
    result = run("-m", "pytest", "-q", "-p", "no:cacheprovider", "tests", cwd=source, env=env)
    assert result.returncode == 0, result.stdout[-3000:]
    assert " passed" in result.stdout and "skipped" not in result.stdout
