"""``python -m gpnerf_core stress <runs or checkpoints> [--cases a,b] [--quick] --out DIR``: evaluate trained models
under graded conditions (the cases and their runner live in ``gpnerf_core.tools.stress``)."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from gpnerf_core.config.arguments import ArgumentParser
from gpnerf_core.errors import ConfigError, NonFiniteError
from gpnerf_core.runtime.io import check_output_folder
from gpnerf_core.runtime.signals import interrupted_by, interruption


def parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="gpnerf_core stress",
        description="Evaluate trained models under graded conditions (stress cases); runs that differ only by "
                    "seed are one method (mean +- std).",
    )
    p.add_argument("paths", nargs="*", type=Path, help="run folders, folders of runs (sweeps) or .pt checkpoints")
    p.add_argument("--cases", default=None, help="comma-separated case names (default: all; --list shows them)")
    p.add_argument("--quick", action="store_true",
                   help="the most severe level of each case on 1 held-out view per scene (a smoke test)")
    p.add_argument("--views-per-scene", type=int, default=None,
                   help="held-out views evaluated per scene (default: all; 1 with --quick)")
    p.add_argument("--out", type=Path, default=None, help="folder for stress.md, stress.csv, stress.json, <case>.png")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier suite in --out")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--list", action="store_true", help="list the registered cases and exit")
    p.add_argument("--merge", action="store_true",
                   help="the paths are --out folders of earlier suites (e.g. one per process): summarise them together")
    return p


def list_cases() -> str:
    """Every registered case; from the plugin index where it knows every plugin (``registry.catalog``: no import)."""
    from gpnerf_core.registry.catalog import stress_levels_text
    from gpnerf_core.registry.listing import listing
    from gpnerf_core.registry.components import get_registry

    known = listing()
    cases = known.stress_cases() if known is not None else {
        name: (case.description, stress_levels_text(case), provider)
        for name, (case, provider) in get_registry().stress_cases.items()
    }
    lines = [f"  {name:<18} [{provider}] {description}\n  {'':<18} levels: {levels}"
             for name, (description, levels, provider) in cases.items()]
    return "stress cases:\n" + "\n".join(lines)


OUTPUTS = ("stress.md", "stress.csv", "stress.json")


def merged_outcomes(folders: list[Path]) -> tuple[list[Any], list[dict[str, Any]]]:
    """The outcomes and models of earlier suites' ``stress.json`` files, in the order given."""
    import json
    import math

    from gpnerf_core.errors import DataError
    from gpnerf_core.tools.stress.runner import Outcome

    outcomes, models = [], []
    for folder in folders:
        path = folder / "stress.json"
        if not path.is_file():
            raise DataError(f"--merge {folder}: no stress.json (expected the --out folder of an earlier suite)")
        try:
            saved = json.loads(path.read_text())
            for o in saved["outcomes"]:
                metrics = {k: float(v) if not isinstance(v, str) else math.nan for k, v in o["metrics"].items()}
                outcomes.append(Outcome(o["model"], o["method"], o["seed"], o["case"], o["level"], o["label"],
                                        metrics, o.get("skipped"), o.get("seconds", 0.0), o.get("error")))
            models += saved.get("models", [])
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise DataError(f"{path}: not a stress suite's results ({type(exc).__name__}: {exc})") from None
    return outcomes, models


def case_names(text: str | None) -> list[str] | None:
    """``--cases a,b`` as names; None (all cases) when the option was not given. An empty list is refused."""
    if text is None:
        return None
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names:
        raise ConfigError(f"--cases {text!r}: expected comma-separated case names (leave --cases out for all of them; "
                          "--list shows them)")
    return names


def write_results(out: Path, outcomes: list[Any], models: list[Any], args: argparse.Namespace, views: int,
                  started: float, interrupted: str | None = None) -> tuple[Any, str]:
    """stress.md, stress.csv and stress.json in ``out`` (each written atomically); the summary and its table."""
    from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
    from gpnerf_core.tools.stress.summary import StressSummary

    summary = StressSummary(outcomes)
    out.mkdir(parents=True, exist_ok=True)
    table = summary.markdown()
    atomic_write_text(out / "stress.md", table)
    atomic_write_text(out / "stress.csv", summary.csv())
    atomic_write_json(out / "stress.json", summary.as_json() | {
        "quick": args.quick, "views_per_scene": views, "seconds": round(time.perf_counter() - started, 1),
        "interrupted": interrupted,
        "models": models if args.merge else [
            {"name": m.name, "method": m.method, "seed": m.seed, "checkpoint": str(m.checkpoint)} for m in models
        ],
    })
    return summary, table


def main(argv: list[str]) -> int:
    import torch

    from gpnerf_core.tools.stress.runner import QUICK_VIEWS_PER_SCENE, choose_cases, models_from_paths, run_suite

    args = parser().parse_args(argv)
    if args.list:
        print(list_cases())
        return 0
    if not args.paths:
        raise ConfigError("gpnerf_core stress: expected run folders or checkpoints to stress (--list shows the cases)")
    if args.out is None:
        raise ConfigError("gpnerf_core stress: --out DIR is required (where stress.md, .csv, .json and plots go)")
    check_output_folder(args.out, "--out")
    if args.out.is_dir() and any((args.out / name).exists() for name in OUTPUTS) and not args.overwrite:
        raise ConfigError(f"--out {args.out} already holds a stress suite's results; use another folder or --overwrite")
    views = args.views_per_scene if args.views_per_scene is not None else (QUICK_VIEWS_PER_SCENE if args.quick else 0)
    if views < 0:
        raise ConfigError(f"--views-per-scene {views}: expected an integer >= 0 (0 = all)")
    if args.threads < 0:
        raise ConfigError(f"--threads {args.threads}: expected an integer >= 0")
    started = time.perf_counter()
    if args.merge:
        outcomes, models = merged_outcomes(args.paths)
        cases = sorted({o.case for o in outcomes if o.case != "clean"})
    else:
        cases = choose_cases(case_names(args.cases))
        models = models_from_paths(args.paths)
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        scratch = Path(tempfile.mkdtemp(prefix="gpnerf_stress_"))
        outcomes = []
        try:
            run_suite(models, cases, quick=args.quick, views_per_scene=views, scratch=scratch, device=device,
                      threads=args.threads, outcomes=outcomes)
        except BaseException as exc:
            stop = interrupted_by(exc)
            if stop is not None and outcomes:  # keep what finished: a rerun of the same suite reads it with --merge
                write_results(args.out, outcomes, models, args, views, started, interrupted=interruption(stop)[0])
                print(f"stress: interrupted; the {len(outcomes)} evaluation(s) that finished are in {args.out} "
                      "(stress.json, marked interrupted)", file=sys.stderr)
            raise
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    summary, table = write_results(args.out, outcomes, models, args, views, started)
    plots = summary.draw(args.out)
    print(table)
    print(f"stress: {len(models)} model(s), {len(cases)} case(s) in {time.perf_counter() - started:.0f} s; "
          f"results and {len(plots)} plot(s) in {args.out}")
    bad = summary.non_finite()
    if bad:
        first = bad[0]
        raise NonFiniteError(
            f"{len(bad)} evaluation(s) gave non-finite metrics; first: {first.model} {first.case} {first.label}: "
            f"{', '.join(first.non_finite)}"
        )
    return 0
