"""Run folders: one live run at a time (a lock naming the holder), no silent mixing with a finished run."""

import json
import os
import socket
import subprocess
import sys

import pytest

from gpnerf_core.runtime.run_folder import LOCK_NAME, RunFolder, RunFolderError


def test_claim_writes_a_lock_naming_the_holder_and_release_removes_it(tmp_path):
    folder = RunFolder(tmp_path / "run")
    assert folder.claim(resuming=False, overwrite=False) == []
    holder = json.loads((tmp_path / "run" / LOCK_NAME).read_text())
    assert holder["pid"] == os.getpid() and holder["host"] == socket.gethostname()
    folder.release()
    assert not (tmp_path / "run" / LOCK_NAME).exists()


def test_a_folder_held_by_a_live_run_is_refused_naming_pid_and_host(tmp_path):
    first = RunFolder(tmp_path / "run")
    first.claim(resuming=False, overwrite=False)
    with pytest.raises(RunFolderError) as error:
        RunFolder(tmp_path / "run").claim(resuming=True, overwrite=True)
    message = str(error.value)
    assert f"pid {os.getpid()} on {socket.gethostname()}" in message and "\n" not in message
    first.release()


def test_a_lock_left_by_a_dead_process_on_this_host_is_taken_over(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / "run").mkdir()
    lock = {"pid": int(dead.stdout), "host": socket.gethostname(), "started": "then", "command": "x"}
    (tmp_path / "run" / LOCK_NAME).write_text(json.dumps(lock))
    with RunFolder(tmp_path / "run") as folder:
        notes = folder.claim(resuming=False, overwrite=False)
        assert any(f"pid {lock['pid']}" in note for note in notes)


def test_a_lock_from_another_host_is_never_taken_over(tmp_path):
    (tmp_path / "run").mkdir()
    lock = {"pid": 1, "host": "elsewhere.example", "started": "then", "command": "x"}
    (tmp_path / "run" / LOCK_NAME).write_text(json.dumps(lock))
    with pytest.raises(RunFolderError, match=f"pid 1 on elsewhere.example.*delete {tmp_path / 'run' / LOCK_NAME}"):
        RunFolder(tmp_path / "run").claim(resuming=False, overwrite=False)


def test_a_finished_run_is_refused_unless_resuming_or_overwriting(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "step_0000001.pt").write_bytes(b"x")
    (run / "metrics.json").write_text("{}")
    with pytest.raises(RunFolderError, match="is not empty .*train.resume=auto .*overwrite=true"):
        RunFolder(run).claim(resuming=False, overwrite=False)
    assert not (run / LOCK_NAME).exists()  # a refused claim leaves no lock behind
    with RunFolder(run) as folder:
        folder.claim(resuming=True, overwrite=False)
        assert (run / "metrics.json").exists()
    with RunFolder(run) as folder:
        notes = folder.claim(resuming=False, overwrite=True)
        assert not (run / "metrics.json").exists() and not (run / "checkpoints").exists() and notes


def test_overwrite_never_deletes_files_a_run_did_not_write(tmp_path):
    (tmp_path / "thesis.tex").write_text("precious")
    with pytest.raises(RunFolderError, match="holds files no run writes \\(first: 'thesis.tex'\\)"):
        RunFolder(tmp_path).claim(resuming=False, overwrite=True)
    assert (tmp_path / "thesis.tex").read_text() == "precious"


def test_an_uncreatable_folder_is_one_line(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(RunFolderError, match="cannot be created"):
        RunFolder(tmp_path / "file" / "run").claim(resuming=False, overwrite=False)


def test_a_run_that_never_trained_does_not_block_its_folder(tmp_path):
    """A run refused after writing its config (e.g. a bad model.init) leaves a folder the fixed command can reuse."""
    for name in ("config.yaml", "config.sha256", "overrides.yaml", "plugins.json"):
        (tmp_path / name).write_text("x")
    with RunFolder(tmp_path) as folder:
        assert folder.claim(resuming=False, overwrite=False) == []


def test_overwrite_never_deletes_what_the_command_reads(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    checkpoint = run / "checkpoints" / "step_0000001.pt"
    checkpoint.write_bytes(b"x")
    (run / "metrics.json").write_text("{}")
    with pytest.raises(RunFolderError, match=r"overwrite=true would delete .*step_0000001\.pt, which this command reads"):
        RunFolder(run).claim(resuming=False, overwrite=True, inputs=[checkpoint])
    assert checkpoint.read_bytes() == b"x" and (run / "metrics.json").exists()


def test_a_folder_without_checkpoints_is_refused_without_advice_to_resume(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "scalars.csv").write_text("step\n")
    with pytest.raises(RunFolderError, match="it holds no checkpoint to resume from; replace it with overwrite=true"):
        RunFolder(run).claim(resuming=False, overwrite=False)
