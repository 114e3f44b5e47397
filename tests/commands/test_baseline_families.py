"""The compared methods' families (``+experiment=baselines/<name>``) are trained, evaluated and rendered by the unchanged
commands: a tiny run of each (two steps, a 32 x 48 layout), its metrics, and one rendered frame of its checkpoint."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gpnerf_core.cli import main as cli_main
from pipeline_check import TINY_CLI

FAMILIES = {
    "semantic_ray": ["model.fine_samples=4"],
    "neuray": ["model.fine_samples=4"],
    "mvsnerf": ["model.num_planes=8", "model.coarse_samples=8", "model.fine_samples=0"],  # its own extractor
}


@pytest.fixture(scope="module", params=sorted(FAMILIES))
def trained(request, tmp_path_factory):
    """The family trained 2 steps by ``run`` in a subprocess: (name, run folder)."""
    name, out = request.param, tmp_path_factory.mktemp(request.param) / "run"
    tiny = [o for o in TINY_CLI if not o.startswith("feature_extractor.")] if name == "mvsnerf" else TINY_CLI
    command = [sys.executable, "-m", "gpnerf_core", "run", f"+experiment=baselines/{name}", *tiny, *FAMILIES[name],
               "train.steps=2", f"out_dir={out}"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    return name, out


def test_run_trains_and_scores_the_family_by_label_rendering(trained):
    name, out = trained
    metrics = json.loads((out / "metrics.json").read_text())
    assert json.loads((out / "plugins.json").read_text())["used"]["model"]["name"] == name
    for split in ("train_heldout", "unseen"):
        assert 0.0 <= metrics["eval"][split]["miou/image_mean_present"] <= 1.0
        assert metrics["eval"][split]["psnr/clamped"] > 0


def test_render_writes_a_frame_of_its_checkpoint(trained, tmp_path):
    name, out = trained
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    try:
        code = cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"])
    except SystemExit as stop:
        code = int(stop.code)
    assert code == 0
    written = json.loads((tmp_path / "video" / "render.json").read_text())
    assert written["frames"] == 1 and Path(tmp_path / "video" / "trajectory.gif").is_file()
