"""Hold a structure-from-motion stage open in the SfM child process, so a test signals while it certainly runs.

``hold_stage(folder, stage)`` writes a ``sitecustomize.py`` into ``folder`` and returns the environment variables that
make every new Python process that finds it (the ``pycolmap-sfm`` child is spawned, so it does) wrap pycolmap's stage
functions: each appends its name to the marker file as it starts, and ``stage`` then waits ``HOLD_SECONDS`` before
the real call. A fixed sleep after the marker raced on a loaded machine (a 10-photo stage can end within it); the
held stage cannot end before the test's signal, and the child ignores SIGINT, so the parent alone decides.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

HOLD_SECONDS = 60.0

_SITECUSTOMIZE = '''
"""Test harness (tests/sfm_stage_hook.py): mark each pycolmap stage as it starts; hold $SFM_HOLD_STAGE open."""
import builtins, os, time

_real_import = builtins.__import__


def _import(name, *args, **kwargs):
    module = _real_import(name, *args, **kwargs)
    if name == "pycolmap" and not getattr(module, "_stage_marked", False):
        module._stage_marked = True
        for function in ("extract_features", "match_sequential", "match_exhaustive", "incremental_mapping"):
            def marked(*a, _real=getattr(module, function), _name=function, **k):
                with open(os.environ["SFM_STAGE_MARKER"], "a") as stream:
                    stream.write(_name + "\\n")
                if _name == os.environ.get("SFM_HOLD_STAGE"):
                    time.sleep(float(os.environ["SFM_HOLD_SECONDS"]))
                return _real(*a, **k)
            setattr(module, function, marked)
    return module


builtins.__import__ = _import
'''


def hold_stage(folder: Path, stage: str) -> dict[str, str]:
    """Environment variables (to add to ``os.environ``) that hold ``stage`` open; the marker file is
    ``folder/stages.txt`` (see ``stage_started``)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(_SITECUSTOMIZE)
    return {"SFM_STAGE_MARKER": str(folder / "stages.txt"), "SFM_HOLD_STAGE": stage,
            "SFM_HOLD_SECONDS": str(HOLD_SECONDS),
            "PYTHONPATH": os.pathsep.join([str(folder), *filter(None, [os.environ.get("PYTHONPATH")])])}


def stage_started(folder: Path, stage: str) -> bool:
    """Whether the SfM child has entered ``stage`` (held there from now on)."""
    marker = folder / "stages.txt"
    return marker.exists() and stage in marker.read_text().split()


def default_sigint() -> None:
    """Give a child process SIGINT's default disposition (``Popen(preexec_fn=...)``). A test run started in the
    background by a script (``nohup``, ``&``) inherits SIGINT ignored, and Python then keeps ignoring it, so a
    Ctrl-C test would see the command run to its end; from a terminal SIGINT is never ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)

