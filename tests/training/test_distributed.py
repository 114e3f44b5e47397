"""torchrun DDP on CPU (gloo, real processes): 2 processes x 1 target view = 1 process x 2 target views."""

import json
import os
import re
import subprocess
import sys

import pytest
import torch

from pipeline_check import child_pids

TINY = [
    "+head=unet", "+loss=dgs", "dataset.num_train_scenes=2", "dataset.num_unseen_scenes=1",
    "dataset.frames_per_scene=6", "dataset.eval_every=3", "dataset.height=32", "dataset.width=48",
    "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "train.log_every=1", "train.steps=3", "train.targets_per_step=2",
    "eval.max_views_per_scene=2", "eval.save_images=1",
    # Without the CPU scale's clip: clipping multiplies every gradient by 4 / norm, and the norm's last bits differ
    # between the two reduction orders, which Adam's first steps turn into differences above the tolerance below.
    "train.grad_clip=0",
]


def launch(nproc, *args, workspace):
    prefix = [sys.executable, "-m", "gpnerf_core"]
    if nproc > 1:
        prefix = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
                  "-m", "gpnerf_core"]
    env = dict(os.environ, GPNERF_CACHE=str(workspace / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1",
               OMP_NUM_THREADS="1")
    return subprocess.run([*prefix, *args], cwd=workspace, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    return tmp_path_factory.mktemp("ddp")


@pytest.fixture(scope="module")
def runs(workspace):
    single = launch(1, "run", *TINY, f"out_dir={workspace / 'single'}", workspace=workspace)
    assert single.returncode == 0, single.stderr[-3000:]
    ddp = launch(2, "run", *TINY, f"out_dir={workspace / 'ddp'}", workspace=workspace)
    assert ddp.returncode == 0, ddp.stderr[-3000:]
    return workspace / "single", workspace / "ddp", ddp


# Parameters whose gradient is zero in exact arithmetic: a conv bias right before an InstanceNorm (the norm removes
# it) and the attention MLP's last bias (the softmax over views removes it). Their float gradients are rounding
# noise, which Adam normalises into steps of up to lr each, differently for different reduction orders.
INVARIANT = re.compile(r"(upconv\d\.conv\.conv|iconv\d\.conv)\.bias$|attn_fc\.2\.bias$")


def test_two_processes_train_the_same_parameters_as_one_with_two_targets(runs):
    single, ddp, _ = runs
    a = torch.load(single / "checkpoints" / "step_0000003.pt", weights_only=True)
    b = torch.load(ddp / "checkpoints" / "step_0000003.pt", weights_only=True)
    assert a["model"].keys() == b["model"].keys()
    largest_lr = max(group["lr"] for group in a["optimizer"]["param_groups"])
    for key, value in a["model"].items():
        if INVARIANT.search(key):
            assert float((b["model"][key] - value).abs().max()) <= 3 * largest_lr, key
        else:
            torch.testing.assert_close(b["model"][key], value, rtol=1e-4, atol=1e-5, msg=key)
    losses_a = [h["loss"] for h in a["history"]]
    losses_b = [h["loss"] for h in b["history"]]
    assert losses_b == pytest.approx(losses_a, rel=1e-5)


def test_ddp_run_records_its_layout_and_only_rank_zero_writes(runs):
    _, ddp, result = runs
    train = json.loads((ddp / "metrics.json").read_text())["train"]
    assert train["world_size"] == 2 and train["targets_per_rank"] == 1 and train["rays_per_step"] == 32
    assert train["backend"] == "gloo"
    assert result.stdout.count("run folder:") == 1  # one summary, from rank 0
    assert "distributed: 2 processes (gloo), 1 target view(s) each, 32 rays per step in all" in result.stderr
    assert len(list((ddp / "checkpoints").glob("*.pt"))) == 1
    assert not (ddp.parent / "outputs").exists()


def test_sharded_evaluation_equals_single_process_evaluation(runs, workspace):
    single, _, _ = runs
    checkpoint = single / "checkpoints" / "step_0000003.pt"
    alone = launch(1, "eval", f"checkpoint={checkpoint}", f"out_dir={workspace / 'eval1'}", workspace=workspace)
    sharded = launch(2, "eval", f"checkpoint={checkpoint}", f"out_dir={workspace / 'eval2'}", workspace=workspace)
    assert alone.returncode == 0 and sharded.returncode == 0, sharded.stderr[-3000:]
    first = json.loads((workspace / "eval1" / "metrics.json").read_text())
    second = json.loads((workspace / "eval2" / "metrics.json").read_text())
    assert second["eval_world_size"] == 2
    for split in ("train_heldout", "unseen"):
        a, b = dict(first["eval"][split]), dict(second["eval"][split])
        a.pop("timing"), b.pop("timing")
        assert a == b, split
    pictures = sorted(p.name for p in (workspace / "eval2" / "images").rglob("*.png"))
    assert pictures == sorted(p.name for p in (workspace / "eval1" / "images").rglob("*.png"))


def test_world_size_that_does_not_divide_the_batch_is_refused_before_training(workspace):
    out = workspace / "odd"
    result = launch(2, "run", *TINY, "train.targets_per_step=3", f"out_dir={out}", workspace=workspace)
    assert result.returncode != 0
    assert "train.targets_per_step=3 is not divisible by the world size 2" in result.stderr
    assert not (out / "checkpoints").exists()


def test_a_loss_set_that_leaves_modules_unused_trains_under_ddp(workspace):
    """+loss=rgb gives the FPN no gradient: DDP is told so, and says nothing about unused parameters."""
    out = workspace / "rgb_only"
    tiny = [o for o in TINY if o not in ("+loss=dgs", "+head=unet")]
    result = launch(2, "run", *tiny, "+loss=rgb", "train.steps=2", "eval.splits=[]", f"out_dir={out}", workspace=workspace)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "unused" not in result.stderr
    assert json.loads((out / "metrics.json").read_text())["train"]["steps"] == 2


def free_port():
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def rank_of(pid):
    try:
        with open(f"/proc/{pid}/environ", "rb") as handle:
            variables = dict(v.split(b"=", 1) for v in handle.read().split(b"\0") if b"=" in v)
    except OSError:
        return None
    return int(variables[b"RANK"]) if b"RANK" in variables else None


def evaluated(folder):
    metrics = json.loads((folder / "metrics.json").read_text())
    return {split: {k: v for k, v in values.items() if k != "timing"} for split, values in metrics["eval"].items()}


def test_a_killed_rank_restarts_the_group_which_resumes_and_ends_as_an_uninterrupted_run(runs, workspace):
    """torchrun --max-restarts=1 + train.resume=auto: SIGKILL rank 1 after the first checkpoint; the agent restarts
    both workers, they resume from the newest checkpoint, and the run ends exactly as the uninterrupted one."""
    import signal
    import time

    _, uninterrupted, _ = runs
    out = workspace / "elastic"
    env = dict(os.environ, GPNERF_CACHE=str(workspace / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1",
               OMP_NUM_THREADS="1")
    agent = subprocess.Popen(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "--max-restarts=1",
         "--monitor-interval=0.2", "-m", "gpnerf_core", "run", *TINY, "train.checkpoint_every=1",
         "train.resume=auto", f"out_dir={out}"],
        cwd=workspace, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    killed = None
    while killed is None and time.monotonic() < deadline and agent.poll() is None:
        if (out / "checkpoints" / "step_0000001.pt").exists():
            killed = next((pid for pid in child_pids(agent.pid) if rank_of(pid) == 1), None)
            if killed is not None:
                os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    stdout, stderr = agent.communicate(timeout=300)
    assert killed is not None, stderr[-3000:]
    assert agent.returncode == 0, stderr[-3000:]
    assert "train.resume=auto: resuming from" in stderr, stderr[-3000:]
    assert evaluated(out) == evaluated(uninterrupted)
    final = torch.load(out / "checkpoints" / "step_0000003.pt", weights_only=True)
    reference = torch.load(uninterrupted / "checkpoints" / "step_0000003.pt", weights_only=True)
    assert all(torch.equal(final["model"][k], v) for k, v in reference["model"].items())
    assert [h["loss"] for h in final["history"]] == [h["loss"] for h in reference["history"]]


def test_two_nodes_on_one_machine_train_as_two_processes_on_one(runs, workspace):
    """Two torchrun agents (--nnodes=2, c10d rendezvous on localhost), one process each, equal one agent with two."""
    _, one_node, _ = runs
    out, port = workspace / "two_nodes", free_port()
    env = dict(os.environ, GPNERF_CACHE=str(workspace / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1",
               OMP_NUM_THREADS="1")
    agents = [
        subprocess.Popen(
            [sys.executable, "-m", "torch.distributed.run", "--nnodes=2", f"--node-rank={node}", "--nproc-per-node=1",
             "--rdzv-backend=c10d", f"--rdzv-endpoint=127.0.0.1:{port}", "--rdzv-id=two-nodes", "-m", "gpnerf_core",
             "run", *TINY, f"out_dir={out}"],
            cwd=workspace, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for node in (0, 1)
    ]
    results = [agent.communicate(timeout=300) for agent in agents]
    assert [agent.returncode for agent in agents] == [0, 0], results[0][1][-2000:] + results[1][1][-2000:]
    train = json.loads((out / "metrics.json").read_text())["train"]
    assert train["world_size"] == 2 and train["targets_per_rank"] == 1
    two = torch.load(out / "checkpoints" / "step_0000003.pt", weights_only=True)
    one = torch.load(one_node / "checkpoints" / "step_0000003.pt", weights_only=True)
    for key, value in one["model"].items():
        torch.testing.assert_close(two["model"][key], value, rtol=1e-6, atol=1e-7, msg=key)
    assert evaluated(out).keys() == evaluated(one_node).keys()
