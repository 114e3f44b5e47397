"""The Slurm paths, run here: a sweep through submitit's local executor (the real submitit code path: each job pickled
and run in its own process, plugins rebuilt there) and the shipped sbatch script under stand-in srun/scontrol."""

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline_check import TINY_CLI

pytest.importorskip("hydra_plugins.hydra_submitit_launcher")

REPO = Path(__file__).resolve().parents[2]
TINY = ["+head=unet", "+loss=dgs", *[o for o in TINY_CLI if not o.startswith("train.rays=")],
        "dataset.num_unseen_scenes=1", "train.steps=2", "train.log_every=1", "eval.max_views_per_scene=1"]


def environment(workspace, **extra):
    return dict(os.environ, GPNERF_CACHE=str(workspace / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1",
                OMP_NUM_THREADS="1", **extra)


def test_a_sweep_through_submitits_local_executor_runs_each_job_in_its_own_process(tmp_path):
    sweep = tmp_path / "sweep"
    result = subprocess.run(
        [sys.executable, "-m", "gpnerf_core", "run", "-m", "hydra/launcher=gpnerf_local", f"hydra.sweep.dir={sweep}",
         *TINY, "train.rays=16,5000"],
        cwd=tmp_path, env=environment(tmp_path), capture_output=True, text=True, timeout=600)
    # job 0 trains; job 1 asks for more rays than an image has: the sweep finishes and exits 2 naming it
    assert result.returncode == 2, result.stderr[-3000:]
    assert f"error: 1 job(s) of the sweep failed (error.json in each): {sweep / '1'}" in result.stderr
    assert json.loads((sweep / "0" / "metrics.json").read_text())["train"]["steps"] == 2
    assert "train.rays=5000 exceeds" in json.loads((sweep / "1" / "error.json").read_text())["error"]
    plugins = json.loads((sweep / "0" / "plugins.json").read_text())  # written by the worker's own registry
    assert "gpnerf_plugins" in json.dumps(plugins)
    logs = sorted(p.name for p in (sweep / ".submitit").rglob("*_log.out"))
    assert len(logs) == 2  # two pickled jobs, each in a submitit worker process


def write_executable(path, text):
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def test_the_sbatch_script_trains_on_two_nodes_and_a_requeued_job_resumes(tmp_path):
    """Stand-ins: ``srun`` starts the command once per node (in parallel, as one task per node would), ``scontrol``
    names this machine. The script runs twice with the same SLURM_JOB_ID: the second time is the requeued job."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    write_executable(bin_dir / "srun", """#!/usr/bin/env bash
while [[ "$1" == --* ]]; do shift; done
pids=()
for ((node = 0; node < SLURM_NNODES; node++)); do SLURM_NODEID=$node SLURM_PROCID=$node "$@" & pids+=($!); done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
exit $status
""")
    write_executable(bin_dir / "scontrol", """#!/usr/bin/env bash
[[ "$1 $2" == "show hostnames" ]] && echo 127.0.0.1
""")
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = environment(tmp_path, PATH=f"{bin_dir}:{Path(sys.executable).parent}:{os.environ['PATH']}",
                      SLURM_JOB_ID="4242", SLURM_NNODES="2", SLURM_JOB_NODELIST="node[1-2]", GPUS_PER_NODE="1",
                      PORT=str(port), RUN_DIR=str(tmp_path / "run"))
    script = REPO / "examples" / "slurm" / "train_multinode.sbatch"
    tiny = [o for o in TINY if o not in ("+head=unet", "+loss=dgs")] + ["train.rays=16"]
    first = subprocess.run(["bash", str(script), *tiny], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    train = json.loads((tmp_path / "run" / "metrics.json").read_text())["train"]
    assert train["world_size"] == 2 and train["steps"] == 2
    assert "train.resume=auto: no checkpoint" in first.stderr
    again = subprocess.run(["bash", str(script), *tiny], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"train.resume=auto: resuming from {tmp_path / 'run' / 'checkpoints' / 'step_0000002.pt'}" in again.stderr
