import json
import sys

import pytest

from gpnerf_core.cli import main


def test_help_lists_commands(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for command in ("run", "eval", "data", "plugins"):
        assert command in out


def test_unknown_command(capsys):
    assert main(["trian"]) == 2
    assert "known commands: run, eval, finetune, fit, render, export, label, view, report, stress, size, bench, data, plugins" in capsys.readouterr().err


def test_data_lists_tools_and_rejects_unknown(capsys):
    assert main(["data"]) == 0
    out = capsys.readouterr().out
    assert all(tool in out for tool in ("check", "features", "import-colmap", "make", "prepare-capture",
                                        "prepare-scannet"))
    assert main(["data", "chek"]) == 2
    assert ("unknown data tool 'chek'; known tools: check, features, import-colmap, make, prepare-capture, "
            "prepare-scannet") in capsys.readouterr().err


def test_data_check_rejects_missing_folder_and_bad_layout(tmp_path, capsys):
    assert main(["data", "check", str(tmp_path / "nope"), "--layout", "replica"]) == 2
    assert "expected a dataset folder" in capsys.readouterr().err
    assert main(["data", "check", str(tmp_path), "--layout", "llff"]) == 2
    assert "invalid choice: 'llff'" in capsys.readouterr().err


def test_data_make_renders_embedded_scenes(tmp_path, capsys):
    root = tmp_path / "scenes"
    args = ["--root", str(root), "--num-train-scenes", "1", "--num-unseen-scenes", "1", "--frames-per-scene", "3",
            "--height", "32", "--width", "48"]
    assert main(["data", "make", *args]) == 0
    assert "embedded scenes ready" in capsys.readouterr().out
    classes = json.loads((root / "classes.json").read_text())
    assert classes["ignore_index"] == 255
    assert len(list(root.rglob("rgb_*.png"))) == 6


def test_eval_requires_checkpoint(capsys):
    assert main(["eval", "+head=unet"]) == 2
    assert "checkpoint=" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["plugins", "extra"]])
def test_plugins_takes_no_arguments(argv, capsys):
    assert main(argv) == 2
    assert "takes no arguments" in capsys.readouterr().err


def test_an_interruption_a_library_turned_into_its_own_error_still_stops_as_an_interruption(monkeypatch, capsys):
    """SIGTERM landing inside OmegaConf's node construction left only an AttributeError whose context was the
    interruption (seen once in CI): the command must still stop as interrupted (143, one line), not with a traceback."""
    import types

    from gpnerf_core import cli
    from gpnerf_core.runtime.signals import Terminated, interrupted_by

    def main(argv):
        try:
            raise Terminated()
        except Terminated:
            raise AttributeError("'NoneType' object has no attribute '_invalidate_flags_cache'")

    monkeypatch.setitem(sys.modules, "gpnerf_core.commands.report", types.SimpleNamespace(main=main))
    assert cli.main(["report"]) == 143
    assert capsys.readouterr().err == "interrupted (SIGTERM): report stopped; the files it had completed stay\n"

    plain = ValueError("no interruption here")
    assert interrupted_by(plain) is None and interrupted_by(None) is None
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as stop:
            raise RuntimeError("cleanup failed") from stop
    except RuntimeError as wrapped:
        assert isinstance(interrupted_by(wrapped), KeyboardInterrupt)

    def broken(argv):
        raise AttributeError("a real bug")

    monkeypatch.setitem(sys.modules, "gpnerf_core.commands.report", types.SimpleNamespace(main=broken))
    with pytest.raises(AttributeError, match="a real bug"):
        cli.main(["report"])
