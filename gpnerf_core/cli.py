"""Command line: ``python -m gpnerf_core <command> [arguments]``; dispatch only.

Each command is the module ``gpnerf_core.commands.<command>`` with ``main(argv) -> exit code``, imported when it is
called (``plugins`` does not pay for torch's training stack). A ``GpnerfError`` a command raises is printed as one line
and exit code 2 (``GPNERF_DEBUG=1`` shows the traceback instead). SIGTERM raises ``signals.Terminated`` inside a command,
so it unwinds like Ctrl-C (children stopped, ``finally`` blocks run); either is one line and exit code 130 or 143.
"""

from __future__ import annotations

import importlib
import os
import sys

from gpnerf_core.errors import GpnerfError
from gpnerf_core.runtime.signals import Terminated, interrupted_by, interruption, sigterm_raises

USAGE = """usage: python -m gpnerf_core <command> [options]

commands:
  run       train on the dataset's training scenes, then evaluate held-out views and unseen scenes
            (Hydra overrides follow, e.g. `run +head=unet +loss=dgs train.steps=200`; `-m` sweeps)
  eval      evaluate a checkpoint with the config it was trained with: `eval checkpoint=<path> [overrides]`
  finetune  fine-tune a checkpoint on some scenes, evaluating their held-out frames along the way:
            `finetune checkpoint=<path> dataset.scenes=[<scene>] train.steps=N [finetune.points=4]`
  fit       fit one scene's per-scene Gaussian model until it has enough (steps, seconds, a target, a plateau),
            recording its curve: `fit [checkpoint=<path>] 'dataset.scenes=[<scene>]' [fit.patience=3] [fit.seconds=60]`
  render    render a novel-view trajectory to MP4, GIF and PNG frames (RGB, depth, semantics side by side):
            `render checkpoint=<path> [render.scene=<name>] [render.path=interpolate|spiral] [render.frames=N]`
  export    the points the model sees in a scene's frames, fused over views, as a PLY point cloud (colour, class):
            `export checkpoint=<path> [export.scene=<name>] [export.frames=eval|train|all] [export.voxel=0.02]`
  label     a model's predicted labels of every frame of a scene, as class-id PNGs (targets for a per-scene model
            on a capture without labels: `dataset.labels_from=<folder>`): `label checkpoint=<path> [label.scene=..]`
  view      serve an interactive web viewer of a checkpoint's novel views (RGB, depth, semantics) on localhost:
            `view checkpoint=<path> [view.scene=<name>] [view.port=8080] [view.host=127.0.0.1]`
  report    tabulate run folders (a sweep, the Table 4 ablation) beside the paper's numbers
  stress    evaluate trained runs under graded conditions (source views, pose noise, corruption, ...):
            `stress <runs> --out DIR [--cases a,b] [--quick]`; `stress --list` names the cases
  size      the smallest model within a tolerance of the configured one on these scenes, by short runs:
            `size +head=unet +loss=dgs [size.steps=300] [size.tolerance=0.02] [size.max_parameters=...]`
  bench     time and size the training step and rendering: `bench size=demo|small|paper [overrides]`
  data      dataset tools: `data` lists them (check a layout, prepare ScanNet, make the embedded scenes)
  plugins   list registered components with provider and version, and plugins that failed to load
"""


COMMANDS = (
    "run", "eval", "finetune", "fit", "render", "export", "label", "view", "report", "stress", "size", "bench", "data",
    "plugins",
)
"""The commands, in the order ``--help`` lists them; each is ``gpnerf_core.commands.<name>``."""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return 0
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"error: unknown command {command!r}; known commands: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    try:
        with sigterm_raises():
            return importlib.import_module(f"gpnerf_core.commands.{command}").main(rest)
    except (KeyboardInterrupt, Terminated) as exc:
        return _interrupted(command, exc)
    except Exception as exc:
        stop = interrupted_by(exc)
        if stop is not None:  # a library turned the interruption into an error of its own while unwinding
            return _interrupted(command, stop)
        if os.environ.get("GPNERF_DEBUG") or not isinstance(exc, (GpnerfError, OSError)):
            raise
        if isinstance(exc, GpnerfError):
            print(f"error: {exc}", file=sys.stderr)
        else:  # an environment fault a command did not name itself: a full disk, a permission
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


def _interrupted(command: str, exc: BaseException) -> int:
    name, code = interruption(exc)
    print(f"interrupted ({name}): {command} stopped; the files it had completed stay", file=sys.stderr)
    return code
