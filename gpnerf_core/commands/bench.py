"""``python -m gpnerf_core bench [size=demo|small|paper[,...]] [repeats=3] [warmup=1] [phases=train,render]
[families=semantic_ray,neuray,mvsnerf] [sweep=rays|views|samples|image] [out_dir=...] [overrides]``.

For each size, the GP-NeRF model and its GNT-only anchor (same backbone, rays and samples; no FPN, semantic field or
head) are measured in fresh processes: a training step (median and minimum over ``repeats`` after ``warmup``, peak
memory, matmul/convolution flops) and the rendering of a whole held-out view. The machine's matmul peak is measured in
the same run. A table goes to stdout, everything to ``<out_dir>/bench.json``. A measurement that runs out of memory is
reported with the peak it reached and the others still run.

``families=<a,b,...>`` also measures compared methods' model families (``+experiment=baselines/<name>``) on each size's
images, views and rays, each beside GP-NeRF in the same run (the ``<family> / GP-NeRF`` rows).

``bench sweep=rays|views|samples|image [size=demo]`` measures one size over a range of one quantity instead
(``gpnerf_core.tools.bench.sweeps``): ``sweep_<name>.csv``, ``.png`` (log-log, the fitted slope of each cost) and ``.json``.

``bench refine=<Gaussians> [refine_threads=1,2]`` measures the refinement step instead: one training step of the
per-scene Gaussian family at that count, at each thread count side by side in one process, split into forward,
backward, density statistics, optimizer and checks (``gpnerf_core.tools.bench.refine``); ``bench.json``'s ``refine``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from gpnerf_core.tools.bench.machine import matmul_peak_gflops
from gpnerf_core.tools.bench.measure import run_measurement
from gpnerf_core.tools.bench.sizes import (
    SIZES,
    VARIANTS,
    check_family_overrides,
    checked_families,
    dropped_overrides,
    get_size,
    variant_overrides,
)
from gpnerf_core.tools.bench.sweeps import Sweep, get_sweep, rows_of, slopes
from gpnerf_core.tools.bench.sweeps import draw as draw_sweep
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.device import machine_info, resolve_device
from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
from gpnerf_core.engine.setup import compose_checked
from gpnerf_core.runtime.run_folder import RunFolder

OWN_KEYS = ("size", "repeats", "warmup", "out_dir", "phases", "sweep", "families", "refine", "refine_threads")
PHASES = ("train", "render")


REFINE_EXPERIMENT = "baselines/semantic_3dgs"
"""The per-scene Gaussian family whose training step ``bench refine=<count>`` times (issue 54's refinement step)."""

def _parse(argv: list[str]) -> tuple[dict[str, str], list[str]]:
    own, overrides = {}, []
    for argument in argv:
        key, sep, value = argument.partition("=")
        if sep and key in OWN_KEYS:
            own[key] = value
        else:
            overrides.append(argument)
    return own, overrides


def _count(own: dict[str, str], key: str, default: int, minimum: int) -> int:
    try:
        value = int(own.get(key, default))
    except ValueError:
        raise ConfigError(f"bench {key}={own[key]!r}: expected an integer >= {minimum}") from None
    if value < minimum:
        raise ConfigError(f"bench {key}={value}: expected an integer >= {minimum}")
    return value


def main(argv: list[str]) -> int:
    if "-h" in argv or "--help" in argv:
        print("usage: python -m gpnerf_core bench" + (__doc__ or "").split("bench", 1)[1].replace("``", ""))
        return 0
    own, overrides = _parse(argv)
    names = [n.strip() for n in own.get("size", "demo").split(",") if n.strip()]
    if not names:
        raise ConfigError(f"bench size={own['size']!r}: expected one or more of {', '.join(SIZES)} (comma-separated)")
    sizes = [get_size(name) for name in names]
    warmup, repeats = _count(own, "warmup", 1, 0), _count(own, "repeats", 3, 1)
    phases = [p.strip() for p in own.get("phases", ",".join(PHASES)).split(",") if p.strip()]
    if not phases or any(p not in PHASES for p in phases):
        raise ConfigError(f"bench phases={own['phases']!r}: expected some of {', '.join(PHASES)}")
    if "refine" in own:
        return run_refine(own, overrides, warmup, repeats)
    if "sweep" in own:
        if len(sizes) != 1:
            raise ConfigError(f"bench sweep={own['sweep']}: one size at a time, got size={own.get('size')}")
        return run_sweep(get_sweep(own["sweep"]), sizes[0], overrides, warmup, repeats, own.get("out_dir"))
    check_family_overrides(overrides)
    variants = [*VARIANTS, *(checked_families(own["families"]) if "families" in own else [])]
    for size in sizes:  # refuse bad overrides before measuring anything
        for variant in variants:
            compose_checked(variant_overrides(size, variant, overrides))
    for variant in variants[len(VARIANTS):]:
        dropped = dropped_overrides(sizes[0], variant, overrides)
        if dropped:
            print(f"bench: note: {variant} does not take {', '.join(dropped)} (left out for it; the other variants "
                  "take them)", file=sys.stderr)
    device = resolve_device(compose(variant_overrides(sizes[0], "gpnerf", overrides)).device)
    out_dir = Path(own.get("out_dir") or Path("outputs") / "bench" / time.strftime("%Y-%m-%d_%H-%M-%S"))
    with RunFolder(out_dir) as folder:
        folder.claim(resuming=False, overwrite=False)
        peak = matmul_peak_gflops(device)
        print(f"{device}: float32 matmul peak {peak:.1f} GFLOP/s", flush=True)
        report: dict[str, Any] = {"device": str(device), "matmul_peak_gflops": peak, "overrides": overrides,
                                  "warmup": warmup, "repeats": repeats, "variants": variants, "sizes": {}}
        for size in sizes:
            entry: dict[str, Any] = {"description": size.description}
            for variant in variants:
                variant_args = variant_overrides(size, variant, overrides)
                entry[variant] = {"overrides": variant_args}
                for phase in PHASES:
                    if phase not in phases:
                        entry[variant][phase] = {"skipped": True}
                        continue
                    print(f"measuring {size.name} {variant} {phase} ...", flush=True)
                    entry[variant][phase] = result = run_measurement(variant_args, phase, warmup, repeats)
                    if result.get("warmup_seconds") is not None and warmup:
                        print(f"  warm-up ({warmup}, compilation included under model.compile): "
                              f"{result['warmup_seconds']:.1f} s", flush=True)
            entry["ratios"] = _ratios(entry)
            entry["family_ratios"] = {family: _ratios(entry, family, "gpnerf") for family in variants[len(VARIANTS):]}
            report["sizes"][size.name] = entry
            atomic_write_json(out_dir / "bench.json", report)
        print(format_table(report))
        for note in flop_notes(report):
            print(note)
        print(f"bench.json: {(out_dir / 'bench.json').resolve()}")
    failed = [(s, v, p, e[v][p]["error"]) for s, e in report["sizes"].items() for v in variants for p in phases
              if "error" in e[v][p]]
    if failed:
        size, variant, phase, error = failed[0]
        more = f" ({len(failed) - 1} more in bench.json)" if len(failed) > 1 else ""
        print(f"error: bench: {size} {variant} {phase} failed: {error}{more}", file=sys.stderr)
    return 1 if failed else 0


def run_refine(own: dict[str, str], overrides: list[str], warmup: int, repeats: int) -> int:
    """``bench refine=<count>``: the refinement step at each of ``refine_threads`` (``tools.bench.refine``)."""
    from gpnerf_core.tools.bench.refine import format_refine, measure_refine, refine_overrides

    count = _count(own, "refine", 0, 1)
    try:
        threads = [int(t) for t in own.get("refine_threads", "1,2").split(",") if t.strip()]
    except ValueError:
        threads = []
    if not threads or min(threads) < 1:
        raise ConfigError(f"bench refine_threads={own['refine_threads']!r}: expected thread counts >= 1 "
                          "(comma-separated)")
    run_overrides = refine_overrides(count, REFINE_EXPERIMENT, overrides)
    cfg = compose_checked(run_overrides)
    out_dir = Path(own.get("out_dir") or Path("outputs") / "bench" / f"refine_{time.strftime('%Y-%m-%d_%H-%M-%S')}")
    with RunFolder(out_dir) as folder:
        folder.claim(resuming=False, overwrite=False)
        print(f"measuring the refinement step at {count} Gaussians, threads {', '.join(map(str, threads))} ...",
              flush=True)
        result = measure_refine(cfg, threads, warmup, repeats)
        machine = machine_info()
        machine.pop("torch_threads")  # each row names its own
        report = {"overrides": run_overrides, "warmup": warmup, "repeats": repeats, "machine": machine,
                  "refine": result}
        atomic_write_json(out_dir / "bench.json", report)
        print(f"CPU: {machine['cpu_model']} ({machine['cpus']} CPUs); {result['gaussians']['start']} Gaussians, "
              f"image {result['image'][0]} x {result['image'][1]}, rasterizer {result['rasterizer']}")
        print(format_refine(result))
        print(f"bench.json: {(out_dir / 'bench.json').resolve()}")
    return 0


def flop_notes(report: dict[str, Any]) -> list[str]:
    """One line per variant whose FLOPs are not reported (``n/a`` in the table), with why."""
    notes = {}
    for entry in report["sizes"].values():
        for variant in report.get("variants", VARIANTS):
            for phase in PHASES:
                note = entry[variant][phase].get("flops_note") if isinstance(entry[variant][phase], dict) else None
                if note:
                    notes.setdefault(variant, note)
    return [f"note: {variant}: FLOPs n/a: {note}" for variant, note in notes.items()]


def run_sweep(sweep: Sweep, size: Any, overrides: list[str], warmup: int, repeats: int, out: str | None) -> int:
    """``bench sweep=<name>``: every point of ``sweep`` for both variants; ``sweep_<name>.csv``, ``.png``, ``.json``."""
    import csv
    import io

    points = {variant: [variant_overrides(size, variant, [*overrides, *extra]) for _, extra in sweep.points]
              for variant in VARIANTS}
    for variant_points in points.values():  # refuse bad overrides before measuring anything
        for point in variant_points:
            compose_checked(point)
    device = resolve_device(compose(points["gpnerf"][0]).device)
    out_dir = Path(out or Path("outputs") / "bench" / f"sweep_{sweep.name}_{time.strftime('%Y-%m-%d_%H-%M-%S')}")
    with RunFolder(out_dir) as folder:
        folder.claim(resuming=False, overwrite=False)
        measured: dict[str, list[dict[str, Any]]] = {variant: [] for variant in VARIANTS}
        for variant in VARIANTS:
            for (x, _), point in zip(sweep.points, points[variant]):
                print(f"measuring {sweep.name}={x:g} {variant} ({', '.join(sweep.phases)}) ...", flush=True)
                measured[variant].append({phase: run_measurement(point, phase, warmup, repeats)
                                          for phase in sweep.phases})
        rows = rows_of(sweep, measured)
        fitted = slopes(sweep, rows)
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(out_dir / f"sweep_{sweep.name}.csv", buffer.getvalue())
        atomic_write_json(out_dir / f"sweep_{sweep.name}.json", {
            "sweep": sweep.name, "size": size.name, "device": str(device), "overrides": overrides,
            "warmup": warmup, "repeats": repeats, "machine": machine_info(), "measured": measured, "slopes": fitted})
        draw_sweep(sweep, rows, out_dir / f"sweep_{sweep.name}.png")
        print(buffer.getvalue().rstrip())
        for variant, costs in fitted.items():
            shown = ", ".join(f"{title} {slope:.2f}" for title, slope in costs.items() if slope is not None)
            print(f"slope of log(cost) against log({sweep.label}), {variant}: {shown}")
        print(f"sweep_{sweep.name}.csv, .png, .json: {out_dir.resolve()}")
    return 1 if any(row["error"] for row in rows) else 0


def _ratios(entry: dict[str, Any], over: str = "gpnerf", under: str = "gnt_only") -> dict[str, float | None]:
    """``over`` (GP-NeRF) over ``under`` (GNT-only): training step time, memory and FLOPs; rendering rays/s per sample
    evaluated, and seconds per frame.

    Times use each variant's fastest repetition: on a shared machine the minimum is the figure least disturbed by
    other work (both median and minimum are in ``bench.json``). The FLOP ratio (matmuls and convolutions, forward and
    backward) is what the step-time ratio comes to where both variants run at the same FLOP/s.
    """
    def value(variant: str, phase: str, key: str) -> float | None:
        return entry[variant][phase].get(key)

    def ratio(a: float | None, b: float | None) -> float | None:
        return a / b if a and b else None

    def rays_per_sample_second(variant: str) -> float | None:
        rays, seconds = value(variant, "render", "rays"), value(variant, "render", "seconds_min")
        samples = value(variant, "render", "samples_per_ray")
        return rays * samples / seconds if rays and seconds and samples else None

    return {
        "train_step_time": ratio(value(over, "train", "seconds_min"), value(under, "train", "seconds_min")),
        "train_peak_memory": ratio(value(over, "train", "peak_memory_mb"), value(under, "train", "peak_memory_mb")),
        "train_flops": ratio(value(over, "train", "flops"), value(under, "train", "flops")),
        "render_samples_per_second": ratio(rays_per_sample_second(over), rays_per_sample_second(under)),
        "render_frame_time": ratio(value(over, "render", "seconds_min"), value(under, "render", "seconds_min")),
    }


def format_table(report: dict[str, Any]) -> str:
    peak = report["matmul_peak_gflops"]
    header = ("size", "variant", "params M", "train s (med/min)", "train MiB", "GFLOP/ray", "GFLOP/s (% peak)",
              "render rays/s", "s/frame", "render MiB")
    rows = [header]
    variants = report.get("variants", VARIANTS)
    for name, entry in report["sizes"].items():
        for variant in variants:
            train, render = entry[variant]["train"], entry[variant]["render"]
            rows.append((name, variant, *_train_cells(train, peak), *_render_cells(render)))
        named = [("GP-NeRF / GNT-only", entry["ratios"])]
        named += [(f"{family} / GP-NeRF", ratios) for family, ratios in entry.get("family_ratios", {}).items()]
        for label, ratios in named:
            flops = "n/a" if ratios["train_flops"] is None and _uncounted(entry, label) else _x(ratios["train_flops"])
            rows.append((name, f"{label} (min)", "", _x(ratios["train_step_time"]), _x(ratios["train_peak_memory"]),
                         flops, "", _x(ratios["render_samples_per_second"]),
                         _x(ratios["render_frame_time"]), ""))
    widths = [max(len(str(row[i])) for row in rows) for i in range(len(header))]
    return "\n".join("  ".join(str(cell).rjust(widths[i]) for i, cell in enumerate(row)) for row in rows)


def _uncounted(entry: dict[str, Any], label: str) -> bool:
    """A ratio row (``<a> / <b>``) one of whose variants has FLOPs not reported (a rasterizing family)."""
    names = {"GP-NeRF": "gpnerf", "GNT-only": "gnt_only"}
    variants = [names.get(part.strip(), part.strip()) for part in label.split(" / ")]
    return any(entry.get(v, {}).get("train", {}).get("flops_note") for v in variants)


def _x(value: float | None) -> str:
    return "" if value is None else f"x{value:.2f}"


def _train_cells(train: dict[str, Any], peak: float) -> tuple[str, ...]:
    if "skipped" in train:
        return ("", "", "", "", "")
    if "error" in train:
        return ("", train["error"], "", "", "")
    params = sum(train["parameters"].values()) / 1e6
    timing = (f"{params:.2f}", f"{train['seconds_median']:.3f}/{train['seconds_min']:.3f}",
              f"{train['peak_memory_mb']:.0f}")
    if train.get("flops") is None:  # a rasterizing family: its FLOPs are not counted (flop_notes says why)
        return (*timing, "n/a", "n/a")
    flops = train["flops"] / train["seconds_median"] / 1e9
    return (*timing, f"{train['flops'] / train['rays'] / 1e9:.3f}", f"{flops:.1f} ({100 * flops / peak:.0f}%)")


def _render_cells(render: dict[str, Any]) -> tuple[str, ...]:
    if "skipped" in render:
        return ("", "", "")
    if "error" in render:
        return (render["error"], "", "")
    return (f"{render['rays'] / render['seconds_median']:.0f}", f"{render['seconds_median']:.3f}",
            f"{render['peak_memory_mb']:.0f}")
