"""The main job end to end on a tiny embedded dataset, through the real command line."""

import json
import os
import subprocess
import sys

import pytest

TINY = [
    "dataset.num_train_scenes=1",
    "dataset.num_unseen_scenes=1",
    "dataset.frames_per_scene=8",
    "dataset.eval_every=4",
    "dataset.height=48",
    "dataset.width=64",
    "model.feature_extractor.widths=[8,8,16,16]",
    "model.feature_extractor.fpn_channels=8",
    "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2",
    "model.coarse_samples=8",
    "model.fine_samples=4",
    "model.num_source_views=2",
    "train.steps=4",
    "train.rays=32",
    "train.log_every=2",
    "eval.chunk_rays=512",
    "eval.max_views_per_scene=1",
    "eval.save_images=1",
    "threads=1",
    "train.loggers=[csv,tensorboard]",
]


def gpnerf(*args, cwd, cache):
    env = dict(os.environ, GPNERF_CACHE=str(cache), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    return subprocess.run(
        [sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    return tmp_path_factory.mktemp("e2e")


@pytest.fixture(scope="module")
def first_run(workspace):
    out = workspace / "run1"
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, f"out_dir={out}", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 0, result.stderr[-3000:]
    return out, result


def test_run_writes_metrics_pictures_and_checkpoint(first_run):
    out, result = first_run
    metrics = json.loads((out / "metrics.json").read_text())
    for split in ("train_heldout", "unseen"):
        values = metrics["eval"][split]
        for protocol in ("miou/image_mean_present", "miou/dataset", "acc/total", "acc/class_mean",
                         "psnr/clamped", "ssim/gaussian11"):
            assert protocol in values, (split, protocol)
        assert 0.0 <= values["miou/image_mean_present"] <= 1.0
        assert "miou/image_mean_present" in values["baseline_majority"]
        assert values["timing"]["seconds_per_frame"] > 0
    assert metrics["train"]["steps"] == 4
    assert metrics["machine"]["cpu_model"] and metrics["machine"]["torch_threads"] >= 1  # figures name their CPU
    assert (out / "config.yaml").is_file() and (out / "plugins.json").is_file()
    assert (out / "training_curves.png").is_file()
    assert len(json.loads((out / "training_curves.json").read_text())) == 2
    assert list((out / "checkpoints").glob("step_0000004.pt"))
    assert list((out / "images" / "train_heldout").glob("*_semantic.png"))
    assert list((out / "images" / "unseen").glob("*_features_pca.png"))
    assert "run folder:" in result.stdout and str(out.resolve()) in result.stdout
    assert not (out.parent / "outputs").exists()  # with out_dir set, nothing lands under outputs/
    assert not (out / ".gpnerf.lock").exists()  # released at the end


def test_checkpoint_explains_itself(first_run):
    import torch

    out, _ = first_run
    state = torch.load(out / "checkpoints" / "step_0000004.pt", weights_only=True)
    assert state["config_sha256"] == (out / "config.sha256").read_text().strip()
    assert state["overrides"][:2] == ["+head=unet", "+loss=dgs"]
    assert state["components"]["head"]["name"] == "unet" and state["components"]["loss"]["name"] == "dgs"
    assert state["components"]["head"]["provider"] == "gpnerf_plugins.heads.plugin"


def test_scalars_go_to_csv_and_tensorboard(first_run):
    import csv

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _ = first_run
    rows = list(csv.DictReader((out / "scalars.csv").open()))
    tags = {row["tag"] for row in rows}
    assert {"train/loss", "train/rgb", "train/ce", "train/sd", "train/dgs", "train/lr/head", "train/rays_per_second",
            "train/peak_memory_mb", "eval/unseen/miou/image_mean_present"} <= tags
    assert [row["step"] for row in rows if row["tag"] == "train/loss"] == ["2", "4"]
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    assert {"train/loss", "eval/train_heldout/psnr/clamped"} <= set(events.Tags()["scalars"])
    assert [e.step for e in events.Scalars("train/loss")] == [2, 4]


def test_second_run_into_a_finished_run_folder_is_refused(first_run, workspace):
    out, _ = first_run
    before = sorted(p.name for p in out.iterdir())
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, f"out_dir={out}", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and f"run folder {out} is not empty" in result.stderr
    assert sorted(p.name for p in out.iterdir()) == before


def strip_timing(values):
    if isinstance(values, dict):
        return {k: strip_timing(v) for k, v in values.items()
                if k not in ("timing", "seconds", "rays_per_second", "wall_seconds", "machine", "checkpoint")}
    return values


def test_same_seed_same_metrics(first_run, workspace):
    out, _ = first_run
    again = workspace / "run2"
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, f"out_dir={again}", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 0, result.stderr[-3000:]
    first = json.loads((out / "metrics.json").read_text())
    second = json.loads((again / "metrics.json").read_text())
    assert strip_timing(first["eval"]) == strip_timing(second["eval"])
    assert first["train"]["final_loss"] == second["train"]["final_loss"]


def test_eval_command_reproduces_run_metrics(first_run, workspace):
    out, _ = first_run
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    evaluated = workspace / "eval"
    # No +head/+loss/model sizes: eval rebuilds the model from the checkpoint's own config.
    result = gpnerf("eval", f"checkpoint={checkpoint}", f"out_dir={evaluated}", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 0, result.stderr[-3000:]
    ran = json.loads((out / "metrics.json").read_text())["eval"]
    evaluated_metrics = json.loads((evaluated / "metrics.json").read_text())["eval"]
    assert strip_timing(ran) == strip_timing(evaluated_metrics)


def test_eval_overrides_apply_and_differences_are_printed(first_run, workspace):
    out, _ = first_run
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    evaluated = workspace / "eval_unseen"
    result = gpnerf("eval", f"checkpoint={checkpoint}", "eval.splits=[unseen]", "eval.save_images=0",
                    f"out_dir={evaluated}", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "differences from the checkpoint's config: eval.save_images: 1 -> 0" in result.stderr
    assert list(json.loads((evaluated / "metrics.json").read_text())["eval"]) == ["unseen"]


def test_unknown_head_lists_known_heads_and_fails(workspace):
    result = gpnerf("run", "+head=nope", "+loss=dgs", cwd=workspace, cache=workspace / "cache")
    assert result.returncode != 0
    assert "unet" in result.stderr and "per_pixel" in result.stderr


def test_unknown_loss_lists_known_losses_and_fails(workspace):
    result = gpnerf("run", "+head=unet", "+loss=nope", cwd=workspace, cache=workspace / "cache")
    assert result.returncode != 0
    assert "dgs" in result.stderr


def test_unknown_command_is_one_line_error(workspace):
    result = gpnerf("trian", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "known commands: run" in result.stderr


def test_damaged_scene_folder_names_the_file_before_training(first_run, workspace):
    import shutil

    [cached] = (workspace / "cache" / "embedded_scenes").iterdir()
    root = workspace / "scenes_copy"
    shutil.copytree(cached, root)
    (root / "layout_00" / "Sequence_1" / "depth" / "depth_3.png").unlink()
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, f"dataset.root={root}", f"out_dir={workspace / 'bad'}",
                    cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 2
    assert "depth_3.png: missing" in result.stderr and f"regenerate: delete {root}" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (workspace / "bad").exists()


def test_plugins_command_lists_kinds(workspace):
    result = gpnerf("plugins", cwd=workspace, cache=workspace / "cache")
    assert result.returncode == 0
    for name in ("resunet_fpn", "gnt_view", "gnt_ray", "unet", "dgs", "embedded", "nearest"):
        assert name in result.stdout


def test_multirun_sweep_runs_every_job_and_report_tabulates_them(workspace):
    sweep = workspace / "sweep"
    tiny = [o for o in TINY if not o.startswith(("train.steps", "eval.save_images"))]
    result = gpnerf(
        "run", "-m", "+experiment=table4_id2,table4_id4", *tiny, "train.steps=1", "eval.save_images=0",
        f"hydra.sweep.dir={sweep}", cwd=workspace, cache=workspace / "cache",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]
    report = gpnerf("report", str(sweep), cwd=workspace, cache=workspace / "cache")
    assert report.returncode == 0, report.stderr
    rows = [line for line in report.stdout.splitlines() if line.startswith("| ") and "run" not in line]
    assert [row.split("|")[17].strip() for row in rows] == ["2", "4"]


def test_a_failing_sweep_job_leaves_its_error_and_the_others_finish(workspace):
    sweep = workspace / "failing_sweep"
    tiny = [o for o in TINY if not o.startswith(("train.steps", "eval.save_images", "model.num_source_views"))]
    result = gpnerf(
        "run", "-m", "+head=unet", "+loss=dgs", "model.num_source_views=2,40", *tiny, "train.steps=1",
        "eval.save_images=0", f"hydra.sweep.dir={sweep}", cwd=workspace, cache=workspace / "cache",
    )
    assert result.returncode == 2
    assert "error: 1 job(s) of the sweep failed (error.json in each)" in result.stderr
    assert (sweep / "0" / "metrics.json").is_file() and not (sweep / "1" / "metrics.json").exists()
    error = json.loads((sweep / "1" / "error.json").read_text())
    assert "model.num_source_views=40" in error["error"] and "model.num_source_views=40" in error["overrides"]
    report = gpnerf("report", str(sweep), cwd=workspace, cache=workspace / "cache")
    assert report.returncode == 0, report.stderr
    rows = [line for line in report.stdout.splitlines() if line.startswith(("| 0 ", "| 1 "))]
    assert rows[0].startswith("| 0 | 0 | gnt | unet | dgs |") and rows[1].startswith("| 1 | failed: model.num_source_views=40")
