"""``view``: serves a checkpoint on localhost until SIGTERM, and refuses bad input in one line (exit 2): a file that
is not a checkpoint, a port in use, an unknown scene."""

import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from pipeline_check import TINY_CLI, gpnerf


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    folder = tmp_path_factory.mktemp("view")
    base = gpnerf("run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=2", f"out_dir={folder / 'base'}",
                  cwd=folder)
    assert base.returncode == 0, base.stderr[-2000:]
    return folder / "base" / "checkpoints" / "step_0000002.pt"


def _leftover_files(folder):
    return [p for p in (folder / "outputs").rglob("*") if p.is_file()] if (folder / "outputs").exists() else []


def test_serves_until_sigterm_and_writes_nothing(checkpoint, tmp_path):
    env = dict(os.environ, GPNERF_CACHE=str(checkpoint.parents[2] / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    process = subprocess.Popen([sys.executable, "-m", "gpnerf_core", "view", f"checkpoint={checkpoint}",
                                "view.port=0", "view.stride=4"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.monotonic() + 120
        while url is None and time.monotonic() < deadline:
            line = process.stdout.readline()
            assert line or process.poll() is None, process.stderr.read()[-2000:]
            found = re.search(r"viewer: open (http://127\.0\.0\.1:\d+) ", line)
            url = found.group(1) if found else None
        assert url is not None, "no URL printed"
        assert "<html" in urllib.request.urlopen(url, timeout=10).read().decode().lower()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 143
        stderr = process.stderr.read()
        assert "Traceback" not in stderr and stderr.strip().splitlines()[-1].startswith("interrupted (SIGTERM)")
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert _leftover_files(tmp_path) == []


def test_a_port_in_use_is_one_line_naming_it(checkpoint, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = gpnerf("view", f"checkpoint={checkpoint}", f"view.port={port}", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == (f"error: view.port={port}: 127.0.0.1:{port} is already in use; "
                                     "choose another view.port")
    assert _leftover_files(tmp_path) == []


def test_bad_input_is_one_line(checkpoint, tmp_path):
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("not a checkpoint\n")
    for args, expected in (
        ([f"checkpoint={not_a_checkpoint}"], str(not_a_checkpoint)),
        ([f"checkpoint={checkpoint}", "view.scene=nowhere"], "view.scene='nowhere' is not a scene"),
        ([f"checkpoint={checkpoint}", "view.port=70000"], "view.port=70000: expected a TCP port"),
        ([f"checkpoint={checkpoint}", "view.preview_stride=0"], "view.preview_stride=0: expected"),
    ):
        result = gpnerf("view", *args, cwd=tmp_path)
        assert result.returncode == 2, result.stderr[-2000:]
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], result.stderr
    assert _leftover_files(tmp_path) == []
