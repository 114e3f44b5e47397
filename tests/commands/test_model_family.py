"""A second model family, a plugin the core does not know (``tests/model_family.py``: IBRNet-style pooling over views,
label rendering), passes the contract kit and is trained, evaluated, rendered and viewed by the unchanged commands."""

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

import model_family
from gpnerf_core.testing import check_plugin
from pipeline_check import TINY_CLI, for_parts

TESTS = Path(__file__).resolve().parents[1]
FAMILY = ["model=pooled_views", "+loss=ce", "model.hidden=16"]


def gpnerf(*args, cwd, popen=False):
    """``python -m gpnerf_core <args>`` with the family installed as a plugin (entry points on), its own scene cache."""
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    env["PYTHONPATH"] = os.pathsep.join([str(cwd / "plugins"), str(TESTS), env.get("PYTHONPATH", "")])
    env["GPNERF_CACHE"] = str(cwd / "cache")
    command = [sys.executable, "-m", "gpnerf_core", *args]
    if popen:
        return subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The family trained 2 steps by ``run``: its folder."""
    root = tmp_path_factory.mktemp("family")
    model_family.install(root / "plugins")
    result = gpnerf("run", *FAMILY, *for_parts(TINY_CLI, "feature_extractor"), "train.steps=2", f"out_dir={root / 'run'}",
                    cwd=root)
    assert result.returncode == 0, result.stderr[-2000:]
    return root / "run"


def test_the_contract_kit_passes_the_second_family():
    results = check_plugin(model_family)
    assert {r.check for r in results if r.component == "model/pooled_views"} >= {"build", "forward", "predict"}
    assert all(r.outcome == "passed" for r in results), [r.message for r in results if r.outcome != "passed"]


def test_run_trains_and_scores_it_and_eval_scores_its_checkpoint_the_same(trained):
    metrics = json.loads((trained / "metrics.json").read_text())
    plugins = json.loads((trained / "plugins.json").read_text())
    assert plugins["used"]["model"] == {"name": "pooled_views", "provider": "gpnerf_test_family", "version": "0.1",
                                        "distribution": model_family.DISTRIBUTION}
    for split in ("train_heldout", "unseen"):
        assert 0.0 <= metrics["eval"][split]["miou/image_mean_present"] <= 1.0  # label rendering is scored
    checkpoint = trained / "checkpoints" / "step_0000002.pt"
    result = gpnerf("eval", f"checkpoint={checkpoint}", f"out_dir={trained.parent / 'eval'}", cwd=trained.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    again = json.loads((trained.parent / "eval" / "metrics.json").read_text())
    for split in ("train_heldout", "unseen"):
        for key in ("miou/image_mean_present", "psnr/clamped", "acc/total"):
            assert again["eval"][split][key] == metrics["eval"][split][key], (split, key)


def test_render_writes_its_trajectory_and_view_serves_it(trained):
    checkpoint = trained / "checkpoints" / "step_0000002.pt"
    out = trained.parent / "video"
    result = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=2", f"out_dir={out}", cwd=trained.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    written = json.loads((out / "render.json").read_text())
    assert written["frames"] == 2 and "legend.png" in written["outputs"] and (out / "trajectory.mp4").is_file()
    process = gpnerf("view", f"checkpoint={checkpoint}", "view.port=0", "view.stride=4", cwd=trained.parent,
                     popen=True)
    try:
        url, deadline = None, time.monotonic() + 120
        while url is None and time.monotonic() < deadline:
            line = process.stdout.readline()
            assert line or process.poll() is None, process.stderr.read()[-2000:]
            found = re.search(r"viewer: open (http://127\.0\.0\.1:\d+) ", line)
            url = found.group(1) if found else None
        assert url is not None and "<html" in urllib.request.urlopen(url, timeout=10).read().decode().lower()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 143  # SIGTERM's exit code
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_bench_measures_a_third_party_family_beside_gp_nerf(tmp_path):
    model_family.install(tmp_path / "plugins")
    tiny = [o for o in TINY_CLI if not o.startswith("eval.")]
    result = gpnerf("bench", "size=demo", "repeats=1", "warmup=0", "phases=render", "families=pooled_views", *tiny,
                    f"out_dir={tmp_path / 'bench'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    demo = json.loads((tmp_path / "bench" / "bench.json").read_text())["sizes"]["demo"]
    family = demo["pooled_views"]
    assert "model=pooled_views" in family["overrides"] and "+loss=ce" in family["overrides"]
    assert family["render"]["rays"] == demo["gpnerf"]["render"]["rays"] > 0
    assert "pooled_views / GP-NeRF (min)" in result.stdout
