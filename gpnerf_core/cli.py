"""Command line: ``python -m gpnerf_core <subcommand> [Hydra overrides]``.

The subcommand is popped first, the plugins are loaded (which makes every registered component a Hydra option),
then Hydra parses the remaining arguments, so overrides, ``+head=...`` and ``-m`` sweeps work unchanged.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Callable

from gpnerf_core.errors import ConfigError, GpnerfError

USAGE = """usage: python -m gpnerf_core <command> [options]

commands:
  run       train on the dataset's training scenes, then evaluate held-out views and unseen scenes
            (Hydra overrides follow, e.g. `run +head=unet +loss=dgs train.steps=200`; `-m` sweeps)
  eval      evaluate a checkpoint with the config it was trained with: `eval checkpoint=<path> [overrides]`
  finetune  fine-tune a checkpoint on some scenes, evaluating their held-out frames along the way:
            `finetune checkpoint=<path> dataset.scenes=[<scene>] train.steps=N [finetune.points=4]`
  render    render a novel-view trajectory to MP4, GIF and PNG frames (RGB, depth, semantics side by side):
            `render checkpoint=<path> [render.scene=<name>] [render.path=interpolate|spiral] [render.frames=N]`
  report    tabulate run folders (a sweep, the Table 4 ablation) beside the paper's numbers
  stress    evaluate trained runs under graded conditions (source views, pose noise, corruption, ...):
            `stress <runs> --out DIR [--cases a,b] [--quick]`; `stress --list` names the cases
  size      the smallest model within a tolerance of the configured one on these scenes, by short runs:
            `size +head=unet +loss=dgs [size.steps=300] [size.tolerance=0.02] [size.max_parameters=...]`
  bench     time and size the training step and rendering: `bench size=demo|small|paper [overrides]`
  data      dataset tools: `data` lists them (check a layout, prepare ScanNet, make the embedded scenes)
  plugins   list registered components with provider and version, and plugins that failed to load
"""


def config_dir() -> str:
    import gpnerf_conf

    return str(Path(gpnerf_conf.__file__).resolve().parent)


def _hydra_entry(task: Callable, argv: list[str], prog: str) -> int:
    import hydra

    from gpnerf_core.config import register_schema
    from gpnerf_core.registry import get_registry

    check_component_choices(argv, get_registry())
    register_schema()
    precheck(argv)
    sys.argv = [prog, *argv]
    from gpnerf_core.run import FAILED_SWEEP_JOBS

    hydra.main(version_base="1.3", config_path=config_dir(), config_name="config")(task)()
    if FAILED_SWEEP_JOBS:
        print(f"error: {len(FAILED_SWEEP_JOBS)} job(s) of the sweep failed (error.json in each): "
              f"{', '.join(FAILED_SWEEP_JOBS)}", file=sys.stderr)
        return 2
    return 0


def check_component_choices(argv: list[str], registry: Any) -> None:
    """Refuse ``[+]head=<name>`` (and every other component group) naming no registered component, in one line that
    lists the known names and any plugin that failed to load, before Hydra says only "could not find"."""
    from gpnerf_core.registry import KINDS

    for argument in argv:
        key, sep, value = argument.partition("=")
        group = key.lstrip("+~")
        if not sep or group not in KINDS or "${" in value:
            continue
        for name in value.split(","):  # a -m sweep over options
            name = name.strip()
            if name and name != "null" and not any(c in name for c in "*?[("):
                registry.get(group, name)


def precheck(argv: list[str]) -> None:
    """Compose and validate the config before Hydra starts (and creates the run folder), so a bad override or value
    is one line and exit code 2. Sweeps (``-m``) and Hydra's own flags are left to Hydra; every job validates too."""
    from gpnerf_core.config import compose
    from gpnerf_core.validation import validate_config

    if any(argument.startswith("-") for argument in argv):
        return
    overrides = [a for a in argv if not a.lstrip("+~").startswith(("hydra.", "hydra/")) or is_search_path(a)]
    try:
        cfg = compose(overrides)
    except GpnerfError:
        raise
    except Exception as exc:
        raise ConfigError(_hydra_message(exc)) from None
    validate_config(cfg)
    if cfg.out_dir:
        check_writable_folder(Path(cfg.out_dir))


def is_search_path(override: str) -> bool:
    """``hydra.searchpath=[file://<dir>]``: where ``+experiment=<name>`` finds a config written outside the package
    (``size``'s ``experiment/sized.yaml``); it changes what composes, so it is kept wherever the config is composed."""
    return override.lstrip("+~").startswith("hydra.searchpath=")


def check_writable_folder(path: Path) -> None:
    """Create ``path`` (Hydra would, with a traceback on failure): one line naming it when that is impossible."""
    from gpnerf_core.run_folder import RunFolderError

    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(
            f"out_dir={path} cannot be created ({exc.strerror or exc}); choose a writable out_dir"
        ) from None


def _hydra_message(exc: BaseException) -> str:
    """A Hydra/OmegaConf error and its causes on one line, without OmegaConf's ``full_key``/``object_type`` tail."""
    parts: list[str] = []
    while exc is not None:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        lines = [line for line in lines if not line.startswith(("full_key:", "object_type=", "reference_type="))]
        text = " ".join(lines)
        if text and text not in parts:
            parts.append(text)
        exc = exc.__cause__
    return "; ".join(parts) or "invalid overrides"


def _run(argv: list[str]) -> int:
    from gpnerf_core.run import run_task

    return _hydra_entry(run_task, argv, "gpnerf_core run")


def _eval(argv: list[str]) -> int:
    from gpnerf_core.run import eval_task

    return _from_checkpoint(eval_task, argv, "eval")


def _finetune(argv: list[str]) -> int:
    from gpnerf_core.run import finetune_task

    return _from_checkpoint(finetune_task, argv, "finetune")


def _render(argv: list[str]) -> int:
    from gpnerf_core.run import render_task

    return _from_checkpoint(render_task, argv, "render")


def _from_checkpoint(task: Callable, argv: list[str], command: str) -> int:
    """Run ``task`` with the config of ``checkpoint=<path>``: its overrides, then the command's."""
    from gpnerf_core.training.checkpoint import read_checkpoint

    given = [a for a in argv if a.startswith("checkpoint=")]
    if not given:
        raise GpnerfError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    stored = read_checkpoint(given[-1].split("=", 1)[1]).get("overrides", [])
    return _hydra_entry(task, merge_overrides(stored, argv), f"gpnerf_core {command}")


def merge_overrides(stored: list[str], given: list[str]) -> list[str]:
    """The checkpoint's overrides (minus run-specific ones) followed by the command's; the command's win.

    A group the checkpoint added with ``+`` stays added when the command switches it without ``+``
    (``head=per_pixel`` after ``+head=unet``). Flags (``-m``) keep their place in front.
    """
    from gpnerf_core.run import RUN_SPECIFIC_KEYS, override_key

    flags = [a for a in given if a.startswith("-")]
    overrides = [a for a in given if not a.startswith("-")]
    user_keys = {override_key(o) for o in overrides}
    added = {override_key(o) for o in stored if o.startswith("+") and not o.startswith("++")}
    kept = [o for o in stored if override_key(o) not in user_keys and override_key(o) not in RUN_SPECIFIC_KEYS]
    adjusted = [f"+{o}" if override_key(o) in added and not o.startswith(("+", "~")) else o for o in overrides]
    return [*flags, *kept, *adjusted]


def _plugins(argv: list[str]) -> int:
    """List components (kind, name, provider, version), disabled plugins and problems; exit 1 on problems."""
    from gpnerf_core.registry import get_registry

    if argv:
        raise GpnerfError(f"plugins takes no arguments, got {' '.join(argv)!r}")
    registry = get_registry()
    rows = [("kind", "name", "provider", "version", "description")]
    for kind, entries in registry.components.items():
        for name in sorted(entries):
            entry = entries[name]
            rows.append((kind, name, entry.provider, entry.version, entry.spec.description))
    for name, (case, provider) in registry.stress_cases.items():
        version = registry.plugins[provider].version if provider in registry.plugins else "builtin"
        rows.append(("stress_case", name, provider, version, case.description))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        print("  ".join(cell.ljust(widths[i]) for i, cell in enumerate(row[:4])) + "  " + row[4])
    if registry.disabled:
        print("\ndisabled:")
        for name in registry.disabled:
            print(f"  {name}")
    if registry.problems:
        print("\nproblems:")
        for problem in registry.problems:
            print(f"  {problem}")
        return 1
    return 0


def _data(argv: list[str]) -> int:
    from gpnerf_core.registry import get_registry

    tools = get_registry().data_tools
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m gpnerf_core data <tool> [arguments]\n\ntools:")
        for name in sorted(tools):
            print(f"  {name:<18} {tools[name][0].description}")
        return 0
    if argv[0] not in tools:
        raise GpnerfError(f"unknown data tool {argv[0]!r}; known tools: {', '.join(sorted(tools)) or '(none)'}")
    return int(tools[argv[0]][0].run(argv[1:]) or 0)


def _bench(argv: list[str]) -> int:
    from gpnerf_core.bench.command import main as bench_main

    return bench_main(argv)


def _report(argv: list[str]) -> int:
    from gpnerf_core.report import main as report_main

    return report_main(argv)


def _size(argv: list[str]) -> int:
    from gpnerf_core.sizing.command import main as size_main

    return size_main(argv)


def _stress(argv: list[str]) -> int:
    from gpnerf_core.stress.cli import main as stress_main

    return stress_main(argv)


COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "run": _run,
    "eval": _eval,
    "finetune": _finetune,
    "render": _render,
    "report": _report,
    "stress": _stress,
    "size": _size,
    "bench": _bench,
    "data": _data,
    "plugins": _plugins,
}


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
        return COMMANDS[command](rest)
    except GpnerfError as exc:
        if os.environ.get("GPNERF_DEBUG"):
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
