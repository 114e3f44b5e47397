"""Issue 31 (nothing lost, nothing silent, no traceback) for the tools: ``size``, ``render``, ``stress``, ``report``
and structure from motion in ``data prepare-capture``."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import imageio.v2 as imageio
import pytest
import yaml
from PIL import Image, ImageSequence

from gpnerf_core.cli import main as cli_main
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.commands import render
from gpnerf_core.tools.sizing.options import check_eval_splits, parse_size_options
from gpnerf_core.tools.stress.runner import models_from_paths
from pipeline_check import TINY_CLI, child_pids, in_process
from sfm_stage_hook import default_sigint, hold_stage, stage_started

SIZE = ["+head=unet", "+loss=dgs", *TINY_CLI, "size.steps=1"]


def gpnerf(*args, cwd, env=None, **kwargs):
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", **(env or {}))
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600, **kwargs)


def one_error_line(stderr: str) -> str:
    """The one line besides render's progress bar, an ``error: ...`` (no traceback)."""
    lines = [line for line in stderr.splitlines()
             if line.strip() and "pybullet build time" not in line and not line.startswith("render:")]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in stderr, stderr[-3000:]
    return lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A finished one-step run (with a head: render shows semantics and a legend)."""
    root = tmp_path_factory.mktemp("trained")
    done = gpnerf("run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=1", f"out_dir={root / 'run'}", cwd=root,
                  env={"GPNERF_CACHE": str(root / "cache")})
    assert done.returncode == 0, done.stderr[-3000:]
    return root / "run"


# ---- 1, 2: size ------------------------------------------------------------------------------------------------


def test_an_empty_knob_list_is_refused_not_read_as_every_knob(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"size.knobs='\[\]': expected at least one knob of model.num_source_views"):
        parse_size_options(["size.knobs=[]"])
    assert cli_main(["size", *SIZE, "size.knobs=[ ]", f"size.out={tmp_path / 'out'}"]) == 2
    assert "leave size.knobs out to size every knob" in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_size_refuses_eval_splits_without_the_split_it_selects_on_before_anything_trains(tmp_path, capsys):
    for splits in (["unseen"], []):
        with pytest.raises(ConfigError, match="expected eval.splits to contain 'train'"):
            check_eval_splits("psnr", splits)
    check_eval_splits("miou", ["train"])
    assert cli_main(["size", *SIZE, "eval.splits=[unseen]", f"size.out={tmp_path / 'out'}"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith("error: eval.splits=[unseen]: size compares trials by miou on the held-out views")
    assert "eval.splits=[train,unseen]" in line
    assert not (tmp_path / "out").exists()  # no runs/, no request.json: nothing trained, nothing written


# ---- 3, 4: render ----------------------------------------------------------------------------------------------


def render_in_process(checkpoint: Path, out: Path, *overrides: str) -> int:
    return in_process("render", f"checkpoint={checkpoint}", "render.frames=4", f"out_dir={out}", *overrides)


@pytest.mark.parametrize("fps", ["0", "-5", "51"])
def test_render_fps_out_of_range_is_refused_before_rendering(trained, tmp_path, capsys, fps):
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    assert render_in_process(checkpoint, tmp_path / "video", f"render.fps={fps}") == 2
    line = one_error_line(capsys.readouterr().err)
    assert line == f"error: render.fps={fps}: expected an integer in [1, 50] (frames per second of the MP4 and the " \
                   "GIF; a GIF plays at most 50)"
    assert not (tmp_path / "video").exists()


def test_a_bad_render_path_or_export_min_views_is_one_line_and_writes_nothing(trained, tmp_path, capsys):
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    assert render_in_process(checkpoint, tmp_path / "bad", "render.path=orbit") == 2
    assert one_error_line(capsys.readouterr().err) == "error: render.path='orbit'; expected one of: interpolate, spiral"
    assert not (tmp_path / "bad").exists()
    refused = tmp_path / "refused"
    assert in_process("export", f"checkpoint={checkpoint}", "export.min_views=99", f"out_dir={refused}") == 2
    assert one_error_line(capsys.readouterr().err).startswith("error: export.min_views=99: only ")
    assert not refused.exists()


def test_gif_delays_are_whole_centiseconds_that_keep_the_rate():
    delays = render.gif_delays_ms(30, 30)
    assert set(delays) == {30, 40} and sum(delays) == 1000  # 30 frames at 30 fps: one second
    assert render.gif_delays_ms(4, 10) == [100] * 4 and render.gif_delays_ms(3, 50) == [20] * 3
    for fps in range(1, render.MAX_FPS + 1):
        delays = render.gif_delays_ms(97, fps)
        assert min(delays) >= 20 and all(d % 10 == 0 for d in delays)  # under 2 cs players show 10 cs
        assert abs(sum(delays) - 97_000 / fps) <= 5


def test_render_writes_gif_and_mp4_at_the_same_fps_and_records_it(trained, tmp_path, capsys):
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    assert render_in_process(checkpoint, tmp_path / "video", "render.fps=30") == 0
    video = tmp_path / "video"
    assert "at 30 fps" in capsys.readouterr().out
    assert json.loads((video / "render.json").read_text())["fps"] == 30
    gif = Image.open(video / "trajectory.gif")
    delays = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
    assert len(delays) == 4 and sum(delays) == 130  # 4 frames at 30 fps, in whole centiseconds
    reader = imageio.get_reader(video / "trajectory.mp4")
    assert reader.get_meta_data()["fps"] == 30 and sum(1 for _ in reader) == 4
    assert sorted(p.name for p in video.iterdir() if p.name.startswith(".")) == []  # no staging folder, no lock


def full_disk_after(limit: int):
    """A writer's stand-in that writes ``limit`` bytes, then fails as a full disk does."""
    def write(path, *args, **kwargs):
        Path(path).write_bytes(b"\0" * limit)
        raise OSError(errno.ENOSPC, "No space left on device")
    return write


def test_a_full_disk_while_writing_the_gif_is_one_line_and_leaves_nothing(trained, tmp_path, capsys, monkeypatch):
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    monkeypatch.setattr(render, "write_gif", full_disk_after(1000))
    assert render_in_process(checkpoint, tmp_path / "video") == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: {tmp_path / 'video' / 'trajectory.gif'}: No space left on device")
    assert not (tmp_path / "video").exists()  # no frames, no MP4, no partial GIF: not even the run folder


def test_a_full_disk_while_feeding_ffmpeg_stops_it_and_leaves_nothing(trained, tmp_path, capsys, monkeypatch):
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    encoders = []

    def first_frame_then_full(stream, pictures):
        encoders.extend(child_pids(os.getpid()))
        stream.write(pictures[0].tobytes())
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(render, "send_frames", first_frame_then_full)
    assert render_in_process(checkpoint, tmp_path / "video") == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: {tmp_path / 'video' / 'trajectory.mp4'}: No space left on device")
    assert not (tmp_path / "video").exists()
    assert encoders and not [pid for pid in encoders if pid in child_pids(os.getpid())], "ffmpeg outlived the render"


def test_render_on_a_really_full_disk_is_one_line_and_leaves_nothing(trained, tmp_path):
    """A 64 KiB tmpfs in a user and mount namespace (skipped where unprivileged namespaces are not allowed)."""
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode:
        pytest.skip("no unprivileged user+mount namespace here to mount a small tmpfs in")
    checkpoint = next((trained / "checkpoints").glob("*.pt"))
    disk = tmp_path / "disk"
    disk.mkdir()
    script = (f"mount -t tmpfs -o size=64k tmpfs {disk} && {sys.executable} -m gpnerf_core render "
              f"checkpoint={checkpoint} render.frames=40 out_dir={disk / 'video'}; code=$?; ls -A {disk}; exit $code")
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1",
                                   GPNERF_CACHE=str(trained.parent / "cache")))
    assert done.returncode == 2, done.stderr[-3000:]
    assert "No space left on device" in one_error_line(done.stderr)
    assert done.stdout.strip() == "", f"left on the full disk: {done.stdout}"


# ---- 5: stress -------------------------------------------------------------------------------------------------


def stopped_run(trained: Path, folder: Path, *, steps: int | None = None) -> Path:
    """What a run that stopped after its last checkpoint leaves: its folder without metrics.json (``steps``: the
    config asked for more steps than the checkpoint reached, so it stopped in training)."""
    shutil.copytree(trained, folder)
    (folder / "metrics.json").unlink()
    if steps is not None:
        config = yaml.safe_load((folder / "config.yaml").read_text())
        config["train"]["steps"] = steps
        (folder / "config.yaml").write_text(yaml.safe_dump(config))
    return folder


def test_stress_uses_the_final_checkpoint_of_a_run_that_stopped_in_evaluation(trained, tmp_path, capsys):
    folder = stopped_run(trained, tmp_path / "runs" / "stopped_in_eval")
    models = models_from_paths([tmp_path / "runs"])
    assert [m.checkpoint for m in models] == [next((folder / "checkpoints").glob("*.pt"))]
    note = capsys.readouterr().err
    assert "training finished (checkpoints/step_0000001.pt) but evaluation did not" in note
    assert "stressing its final checkpoint step_0000001.pt (step 1)" in note


def test_stress_says_why_it_passes_over_a_run_that_stopped_in_training(trained, tmp_path, capsys):
    stopped_run(trained, tmp_path / "runs" / "stopped_in_training", steps=5)
    with pytest.raises(DataError, match="training stopped at step 1 of 5") as refused:
        models_from_paths([tmp_path / "runs"])
    assert "a partly trained model is not stressed unless its checkpoint is given" in str(refused.value)
    assert "skipping" in capsys.readouterr().err


# ---- 6: report -------------------------------------------------------------------------------------------------


def write_config(folder: Path, steps: int = 4) -> Path:
    folder.mkdir(parents=True)
    config = {"head": {"name": "unet"}, "loss": {"name": "dgs"}, "seed": 0, "train": {"steps": steps}}
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    return folder


def test_report_lists_runs_without_metrics_with_what_their_files_show(tmp_path, capsys):
    finished = write_config(tmp_path / "runs" / "finished")
    (finished / "metrics.json").write_text(json.dumps(
        {"train": {"steps": 4, "seconds": 1.0}, "eval": {"train_heldout": {"miou/image_mean_present": 0.5}}}))
    write_config(tmp_path / "runs" / "died_early")
    in_training = write_config(tmp_path / "runs" / "in_training")
    (in_training / "checkpoints").mkdir()
    (in_training / "checkpoints" / "step_0000002.pt").write_bytes(b"")
    in_eval = write_config(tmp_path / "runs" / "in_eval", steps=2)
    shutil.copytree(in_training / "checkpoints", in_eval / "checkpoints")
    running = write_config(tmp_path / "runs" / "running")
    (running / ".gpnerf.lock").write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                                      "started": "2026-01-01 00:00:00"}))
    render_folder = write_config(tmp_path / "runs" / "a_render")
    (render_folder / "render.json").write_text("{}")
    export_folder = write_config(tmp_path / "runs" / "an_export")
    (export_folder / "export.json").write_text("{}")

    assert cli_main(["report", str(tmp_path / "runs")]) == 0
    captured = capsys.readouterr()
    rows = {line.split(" | ")[0].strip("| "): line for line in captured.out.splitlines()[2:]}
    assert set(rows) == {"finished", "died_early", "in_training", "in_eval", "running"}  # a render, an export: no runs
    assert "| 50.00 |" in rows["finished"]
    assert "unfinished: no metrics.json and no checkpoint: it stopped" in rows["died_early"]
    assert "unfinished: no metrics.json: training stopped at step 2 of 4" in rows["in_training"]
    assert "resume it with train.resume=auto" in rows["in_training"]
    assert "training finished (checkpoints/step_0000002.pt) but evaluation did not" in rows["in_eval"]
    assert f"held by a running process (pid {os.getpid()}" in rows["running"]
    assert captured.err.strip() == ("note: 4 of 5 run folder(s) have no metrics.json (failed or unfinished: their "
                                    "rows say why); the table's numbers are the other runs'")


# ---- 7: structure from motion interrupted ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """10 views 9 degrees apart of the embedded orbit (as tests/plugins/test_capture_prepare.py makes them)."""
    from gpnerf_plugins.datasets.embedded import SEQUENCE, SceneSetParams, generate

    root = tmp_path_factory.mktemp("orbit")
    sequence = generate(SceneSetParams(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=40, height=240,
                                       width=320, seed=0), root / "set") / "layout_00" / SEQUENCE
    folder = root / "photos"
    folder.mkdir()
    for i in range(10):
        shutil.copyfile(sequence / "rgb" / f"rgb_{i}.png", folder / f"rgb_{i}.png")
    return folder


@pytest.mark.parametrize("signum, stage, whole_group", [
    (signal.SIGINT, "match_sequential", True),  # Ctrl-C: the terminal signals the whole process group
    (signal.SIGTERM, "incremental_mapping", False),  # kill <pid>
])
def test_a_signal_during_structure_from_motion_is_one_line_and_leaves_nothing(photos, tmp_path, signum, stage,
                                                                               whole_group):
    hook = tmp_path / "hook"
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", **hold_stage(hook, stage))
    process = subprocess.Popen([sys.executable, "-m", "gpnerf_core", "data", "prepare-capture", str(photos), "--out",
                                str(out / "scene"), "--threads", "1"], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True,
                               preexec_fn=default_sigint)  # as from a terminal, whatever pytest inherited
    deadline = time.monotonic() + 300
    while process.poll() is None and time.monotonic() < deadline and not stage_started(hook, stage):
        time.sleep(0.01)
    assert process.poll() is None, f"prepare-capture ended before {stage}: {process.stderr.read()[-2000:]}"
    children = child_pids(process.pid)
    if whole_group:
        os.killpg(process.pid, signum)
    else:
        process.send_signal(signum)
    stderr = process.communicate(timeout=120)[1]
    name = signal.Signals(signum).name
    assert process.returncode == 128 + signum, stderr[-3000:]
    lines = [line for line in stderr.splitlines() if line.strip() and "pybullet build time" not in line]
    assert len(lines) == 1 and lines[0].startswith(f"interrupted ({name})"), stderr[-3000:]
    assert os.listdir(out) == [], "a .scene.partial-* folder was left behind"
    time.sleep(0.2)
    assert not [pid for pid in children if Path(f"/proc/{pid}").exists() and
                Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"], "the SfM process lives on"
