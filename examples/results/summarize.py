"""The tables of docs/results_detail.md from the run folders ``regenerate.sh`` wrote (reads ``metrics.json`` only):

    python examples/results/summarize.py [WORK, default /tmp/gpnerf-results] > WORK/summary.md
    python examples/results/summarize.py examples/results/records     # the committed records (the records stage)

Sections: Table 4 (per seed, mean +- sample std, the orderings that hold beyond the seed spread), the methods of the
speed-accuracy chart, the compared methods' families (Table 1's generalization rows and the paper's orderings), each
field per pixel and with GP-NeRF's U-Net decoding, the layout-count curve, Table 1's rows (generalized and fine-tuned)
on each generalized protocol the ``protocol`` stage ran, where the samples go (the samplers), the
instance head and DM-NeRF against the connected-components baseline, fine-tuning, and when a scene needs its own model
(Semantic-NeRF from scratch against GP-NeRF zero-shot and fine-tuned). A missing run is
named, never skipped silently.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import statistics
import sys
from pathlib import Path
from typing import Any, Callable

SEEDS = (0, 1, 2)
HELD, UNSEEN = "train_heldout", "unseen"
MIOU = "miou/image_mean_present"


def load(runs: Path, name: str) -> dict[str, Any] | None:
    path = runs / name / "metrics.json"
    return json.loads(path.read_text()) if path.is_file() else None


def mean_std(values: list[float], scale: float = 1.0, digits: int = 2) -> str:
    if not values:
        return "not run"
    values = [v * scale for v in values]
    if len(values) == 1:
        return f"{values[0]:.{digits}f} (n=1)"
    return f"{statistics.fmean(values):.{digits}f} +- {statistics.stdev(values):.{digits}f}"


def column(runs: list[dict[str, Any]], read: Callable[[dict[str, Any]], Any]) -> list[float]:
    return [float(v) for run in runs if (v := read(run)) is not None]


def split(name: str, key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda m: m["eval"].get(name, {}).get(key)


def timing(key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda m: m["eval"].get(HELD, m["eval"].get(UNSEEN, {})).get("timing", {}).get(key)


def table4(runs: Path) -> list[str]:
    lines = ["## Table 4 (IDs 1-5, seeds 0-2)", "",
             "| ID | held-out mIoU x100 (seeds 0, 1, 2) | mean +- std | unseen mIoU x100 (seeds 0, 1, 2) | mean +- std "
             "| PSNR held-out | train s | missing |", "|---|---|---|---|---|---|---|---|"]
    per_id: dict[int, dict[int, dict[str, Any]]] = {}
    for table_id in range(1, 6):
        found = {s: m for s in SEEDS if (m := load(runs, f"id{table_id}_s{s}")) is not None}
        per_id[table_id] = found
        ms = [found[s] for s in SEEDS if s in found]
        held = [100 * m["eval"][HELD][MIOU] for m in ms]
        unseen = [100 * m["eval"][UNSEEN][MIOU] for m in ms]
        missing = ", ".join(f"seed {s}" for s in SEEDS if s not in found) or ""
        lines.append(f"| {table_id} | {', '.join(f'{v:.2f}' for v in held)} | {mean_std(held)} | "
                     f"{', '.join(f'{v:.2f}' for v in unseen)} | {mean_std(unseen)} | "
                     f"{mean_std(column(ms, split(HELD, 'psnr/clamped')))} | "
                     f"{mean_std(column(ms, lambda m: m['train']['seconds']), digits=0)} | {missing} |")
    lines += ["", "Orderings (a difference taken seed by seed holds when it has one sign at every seed and a mean above "
              "twice its standard error, sd / sqrt(n)):", "",
              "| step | held-out: per seed; mean | holds? | unseen: per seed; mean | holds? |", "|---|---|---|---|---|"]
    steps = (("joint attention (ID 1 -> 2)", 1, 2), ("S.D without the block (ID 2 -> 3)", 2, 3),
             ("the gradient block (ID 3 -> 4)", 3, 4), ("D.G on top (ID 4 -> 5)", 4, 5))
    for title, a, b in steps:
        cells = []
        for name in (HELD, UNSEEN):
            seeds = [s for s in SEEDS if s in per_id[a] and s in per_id[b]]
            diffs = [100 * (per_id[b][s]["eval"][name][MIOU] - per_id[a][s]["eval"][name][MIOU]) for s in seeds]
            cells += paired_cells(diffs)
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    return lines


def paired_cells(diffs: list[float]) -> list[str]:
    """Two table cells for differences taken seed by seed: ``per seed; **mean**`` and whether it ``holds``."""
    if not diffs:
        return ["not run", holds(diffs)]
    return [f"{', '.join(f'{d:+.1f}' for d in diffs)}; **{statistics.fmean(diffs):+.1f}**", holds(diffs)]


def holds(diffs: list[float]) -> str:
    if len(diffs) < 2:
        return "n/a"
    one_sign = all(d > 0 for d in diffs) or all(d < 0 for d in diffs)
    mean, error = statistics.fmean(diffs), statistics.stdev(diffs) / math.sqrt(len(diffs))
    if one_sign and abs(mean) > 2 * error:
        return "yes"
    return "no (one sign, within 2 se)" if one_sign else "no (signs differ)"


METHODS = (("GP-NeRF (U-Net head, S.D + D.G: Table 4 ID 5, the main job)", "id5"),
           ("GP-NeRF sized (bounds 0.59 / 5.70 m, 2 blocks, no fine samples, 3 views)", "sized"),
           ("per-pixel head + cross-entropy (`baselines/label_rendering`)", "label_rendering"),
           ("GNT alone (`baselines/gnt`: RGB only)", "gnt"),
           ("MVSplat, label rendering (`baselines/mvsplat`)", "mvsplat"),
           ("MVSplat + GP-NeRF's U-Net head (`baselines/mvsplat_unet`)", "mvsplat_unet"))


def methods(runs: Path) -> list[str]:
    lines = ["## Methods (seeds 0-2)", "",
             "| method | mIoU held-out | mIoU unseen | PSNR held-out | params (M) | train s | rays/s | s/frame | peak MB "
             "| missing |", "|---|---|---|---|---|---|---|---|---|---|"]
    for title, prefix in METHODS:
        found = {s: m for s in SEEDS if (m := load(runs, f"{prefix}_s{s}")) is not None}
        ms = list(found.values())
        missing = ", ".join(f"seed {s}" for s in SEEDS if s not in found)
        lines.append(
            f"| {title} | {mean_std(column(ms, split(HELD, MIOU)), digits=3)} | "
            f"{mean_std(column(ms, split(UNSEEN, MIOU)), digits=3)} | {mean_std(column(ms, split(HELD, 'psnr/clamped')))} | "
            f"{mean_std(column(ms, lambda m: m.get('parameters', {}).get('total', 0) / 1e6), digits=3)} | "
            f"{mean_std(column(ms, lambda m: m['train']['seconds']), digits=0)} | "
            f"{mean_std(column(ms, lambda m: m['train']['rays_per_second']), digits=0)} | "
            f"{mean_std(column(ms, timing('seconds_per_frame')))} | {mean_std(column(ms, timing('peak_memory_mb')), digits=0)} "
            f"| {missing} |")
    return lines


# GP-NeRF's Table 1 (generalization, mIoU x100: Replica, ScanNet) beside each method's run prefix, in the paper's order.
TABLE1 = (("GP-NeRF (`+head=unet +loss=dgs`: Table 4 ID 5's config)", "id5", (48.53, 59.92)),
          ("Semantic-Ray (`baselines/semantic_ray`)", "semantic_ray", (41.59, 57.15)),
          ("NeuRay + semantic head (`baselines/neuray`)", "neuray", (35.90, 51.03)),
          ("MVSNeRF + semantic head (`baselines/mvsnerf`)", "mvsnerf", (23.41, 39.82)))


def same_prefix(prefix: str) -> str:
    return prefix


def baselines(runs: Path, run_prefix: Callable[[str], str] = same_prefix,
              heading: str = "The compared methods (Table 1's generalization rows, seeds 0-2)") -> list[str]:
    """Table 1's generalization rows on the embedded scenes (held-out views of the training layouts, and the unseen
    layouts), and whether each of the paper's orderings holds beyond the seed spread (paired by seed, unseen mIoU).
    ``run_prefix`` maps a method's prefix in ``TABLE1`` to its runs' (the protocol's runs have their own names)."""
    lines = [f"## {heading}", "",
             "| method | total acc unseen | class-mean acc unseen | mIoU held-out | mIoU unseen | PSNR held-out "
             "| PSNR unseen | SSIM unseen | params (M) | train s | s/frame | paper mIoU (Replica / ScanNet) | missing |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    found_by = {}
    for title, prefix, paper in TABLE1:
        found = {s: m for s in SEEDS if (m := load(runs, f"{run_prefix(prefix)}_s{s}")) is not None}
        found_by[prefix] = found
        ms = list(found.values())
        missing = ", ".join(f"seed {s}" for s in SEEDS if s not in found)
        lines.append(
            f"| {title} | {mean_std(column(ms, split(UNSEEN, 'acc/total')), digits=3)} | "
            f"{mean_std(column(ms, split(UNSEEN, 'acc/class_mean')), digits=3)} | "
            f"{mean_std(column(ms, split(HELD, MIOU)), digits=3)} | {mean_std(column(ms, split(UNSEEN, MIOU)), digits=3)} | "
            f"{mean_std(column(ms, split(HELD, 'psnr/clamped')))} | {mean_std(column(ms, split(UNSEEN, 'psnr/clamped')))} | "
            f"{mean_std(column(ms, split(UNSEEN, 'ssim/gaussian11')), digits=3)} | "
            f"{mean_std(column(ms, lambda m: m.get('parameters', {}).get('total', 0) / 1e6), digits=3)} | "
            f"{mean_std(column(ms, lambda m: m['train']['seconds']), digits=0)} | "
            f"{mean_std(column(ms, timing('seconds_per_frame')))} | {paper[0]:.2f} / {paper[1]:.2f} | {missing} |")
    lines += ["", "| the paper's ordering (unseen mIoU, paired by seed) | differences x100 | holds beyond the spread |",
              "|---|---|---|"]
    for (title_a, a, _), (title_b, b, _) in zip(TABLE1, TABLE1[1:]):
        seeds = [s for s in SEEDS if s in found_by[a] and s in found_by[b]]
        diffs = [100 * (found_by[a][s]["eval"][UNSEEN][MIOU] - found_by[b][s]["eval"][UNSEEN][MIOU]) for s in seeds]
        shown = ", ".join(f"{d:+.1f}" for d in diffs) or "not run"
        lines.append(f"| {title_a.split(' (')[0]} > {title_b.split(' (')[0]} | {shown} | {holds(diffs)} |")
    return lines


GRID = (("GP-NeRF's field (GNT + semantic field)", "label_rendering", "id5"),
        ("Semantic-Ray", "semantic_ray", "semantic_ray_unet"),
        ("NeuRay + semantic head", "neuray", "neuray_unet"),
        ("MVSNeRF + semantic head", "mvsnerf", "mvsnerf_unet"))


def grid(runs: Path) -> list[str]:
    """Each family's field scored per pixel and with GP-NeRF's context-aware U-Net decoding, seed 0 (GP-NeRF's own
    per-pixel variant is the per-pixel head on its rendered features, ``baselines/label_rendering``)."""
    lines = ["## Fields x decoding (seed 0): per pixel against GP-NeRF's context-aware U-Net head", "",
             "| field | per pixel: mIoU held-out / unseen | U-Net head: mIoU held-out / unseen | U-Net - per pixel (unseen) |",
             "|---|---|---|---|"]
    for title, per_pixel, unet in GRID:
        a, b = load(runs, f"{per_pixel}_s0"), load(runs, f"{unet}_s0")

        def cell(m: dict[str, Any] | None) -> str:
            return "not run" if m is None else f"{m['eval'][HELD][MIOU]:.3f} / {m['eval'][UNSEEN][MIOU]:.3f}"

        gain = f"{b['eval'][UNSEEN][MIOU] - a['eval'][UNSEEN][MIOU]:+.3f}" if a and b else "-"
        lines.append(f"| {title} | {cell(a)} | {cell(b)} | {gain} |")
    return lines


LAYOUT_COUNTS = (4, 8, 16, 32)


def layouts(runs: Path) -> list[str]:
    """GP-NeRF against the number of training layouts (steps growing with them, seeds 0-2), scored on 4 unseen
    layouts, and whether each wider count raises unseen mIoU and PSNR over each narrower one beyond the seed spread."""
    lines = ["## Training layouts (GP-NeRF, 150 steps per layout, seeds 0-2): the generalized protocol's curve", "",
             "| layouts | steps | mIoU held-out | mIoU unseen, 4 layouts (seeds 0, 1, 2) | mean +- std | PSNR unseen "
             "| SSIM unseen | train s | missing |", "|---|---|---|---|---|---|---|---|---|"]
    found: dict[int, dict[int, dict[str, Any]]] = {}
    for count in LAYOUT_COUNTS:
        found[count] = {s: m for s in SEEDS if (m := load(runs, f"layouts_n{count}_s{s}")) is not None}
        ms = list(found[count].values())
        missing = ", ".join(f"seed {s}" for s in SEEDS if s not in found[count])
        unseen = column(ms, split(UNSEEN, MIOU))
        lines.append(f"| {count} | {150 * count} | {mean_std(column(ms, split(HELD, MIOU)), digits=3)} | "
                     f"{', '.join(f'{v:.3f}' for v in unseen)} | {mean_std(unseen, digits=3)} | "
                     f"{mean_std(column(ms, split(UNSEEN, 'psnr/clamped')))} | "
                     f"{mean_std(column(ms, split(UNSEEN, 'ssim/gaussian11')), digits=3)} | "
                     f"{mean_std(column(ms, lambda m: m['train']['seconds']), digits=0)} | {missing} |")
    lines += ["", "Wider against narrower, paired by seed (holds: one sign at every seed, mean above twice its standard "
              "error):", "", "| step | unseen mIoU x100: per seed; mean | holds? | unseen PSNR (dB): per seed; mean "
              "| holds? |", "|---|---|---|---|---|"]
    pairs = sorted(itertools.combinations(LAYOUT_COUNTS, 2),
                   key=lambda pair: (LAYOUT_COUNTS.index(pair[1]) - LAYOUT_COUNTS.index(pair[0]), pair[0]))
    for a, b in pairs:  # each step up first, then the wider ones
        seeds = [s for s in SEEDS if s in found[a] and s in found[b]]
        cells = []
        for key, scale in ((MIOU, 100.0), ("psnr/clamped", 1.0)):
            diffs = [scale * (found[b][s]["eval"][UNSEEN][key] - found[a][s]["eval"][UNSEEN][key]) for s in seeds]
            cells += paired_cells(diffs)
        lines.append(f"| {a} -> {b} layouts | " + " | ".join(cells) + " |")
    return lines


SAMPLERS = (("uniform: 24 coarse + 8 fine (ID 5, the main job)", "id5"),
            ("depth from the coarse pass (model.sampler=depth)", "sampler_first_pass"),
            ("depth from a feature sweep (+depth_source=cost_volume): one pass, 8 samples", "sampler_cost_volume"),
            ("depth from the recorded depth (+depth_source=source_depth): one pass, 8 samples", "sampler_source_depth"))


def samplers(runs: Path) -> list[str]:
    """The main job's config trained and evaluated with each sampling, seeds 0-2: accuracy and render time."""
    lines = ["## Where the samples go (the main job's config, seeds 0-2)", "",
             "| sampling | mIoU held-out | mIoU unseen | PSNR held-out | PSNR unseen | depth AbsRel unseen "
             "| eval s/frame | train s | missing |", "|---|---|---|---|---|---|---|---|---|"]
    for title, prefix in SAMPLERS:
        found = {s: m for s in SEEDS if (m := load(runs, f"{prefix}_s{s}")) is not None}
        ms = list(found.values())
        missing = ", ".join(f"{prefix}_s{s}" for s in SEEDS if s not in found) or "-"
        lines.append(f"| {title} | {mean_std(column(ms, split(HELD, MIOU)), digits=3)} | "
                     f"{mean_std(column(ms, split(UNSEEN, MIOU)), digits=3)} | "
                     f"{mean_std(column(ms, split(HELD, 'psnr/clamped')))} | "
                     f"{mean_std(column(ms, split(UNSEEN, 'psnr/clamped')))} | "
                     f"{mean_std(column(ms, split(UNSEEN, 'depth/abs_rel')), digits=3)} | "
                     f"{mean_std(column(ms, timing('seconds_per_frame')))} | "
                     f"{mean_std(column(ms, lambda m: m['train']['seconds']), digits=0)} | {missing} |")
    return lines


def curve_points(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """A run's accuracy curve by step: ``finetune.curve`` (fine-tuning) or ``eval_curve`` (``eval.every_steps``)."""
    points = (metrics.get("finetune") or {}).get("curve") or metrics.get("eval_curve") or []
    return sorted(points, key=lambda point: point["step"])


def at(point: dict[str, Any], key: str) -> float:
    """A curve point's value of ``key``: flat in ``finetune.curve``, under the split in ``eval_curve`` (the scene's
    held-out frames here)."""
    return float(point[key] if key in point else point[HELD][key])


LONG_STEPS = 8000
"""Steps of the long Semantic-NeRF run (``semantic_nerf_unseen_8k_s0``): whether the per-scene model ever catches up."""


def per_scene(runs: Path) -> list[str]:
    """When a scene needs its own model (unseen_00): GP-NeRF zero-shot (its fine-tuning's step 0) and fine-tuned
    (ID 5's runs, ``finetune`` stage) against Semantic-NeRF fitted from scratch on the same frames (2000 steps x seeds
    0-2, one ``LONG_STEPS`` run, its grid option's 2000 steps x seeds 0-2) and semantic 3D Gaussian splatting (2000
    steps x seeds 0-2, ``per_scene_gaussians``), by steps and training seconds; a crossover is the first per-scene point
    at or above GP-NeRF's mean mIoU, zero-shot and fine-tuned."""
    lines = ["## When a scene needs its own model (unseen_00, seeds 0-2): accuracy against steps and seconds", "",
             "| method | seed | step | train s | mIoU (per image) | PSNR |", "|---|---|---|---|---|---|"]
    finals = []
    for seed in SEEDS:
        tuned = load(runs, f"finetune_id5_s{seed}")
        if tuned is None:
            lines.append(f"| GP-NeRF (ID 5) fine-tuned | {seed} | not run ||||")
            continue
        for point in curve_points(tuned):
            name = "GP-NeRF (ID 5), zero-shot" if point["step"] == 0 else "GP-NeRF (ID 5) fine-tuned"
            lines.append(f"| {name} | {seed} | {point['step']} | {point['train_seconds']:.0f} | "
                         f"{at(point, MIOU):.3f} | {at(point, 'psnr/clamped'):.2f} |")
        finals.append(at(curve_points(tuned)[-1], MIOU))
    zero_shot = [at(curve_points(t)[0], MIOU) for t in (load(runs, f"finetune_id5_s{seed}") for seed in SEEDS)
                 if t is not None and curve_points(t)[0]["step"] == 0]
    crossings = []
    for name, label in (("semantic_nerf_unseen", "Semantic-NeRF from scratch"),
                        ("semantic_nerf_unseen_8k", f"Semantic-NeRF from scratch, {LONG_STEPS} steps"),
                        ("semantic_nerf_grid_unseen", "Semantic-NeRF's grid option from scratch"),
                        ("semantic_3dgs_unseen", "Semantic 3DGS from scratch")):
        for seed in SEEDS:
            fitted = load(runs, f"{name}_s{seed}")
            if fitted is None:
                if name != "semantic_nerf_unseen_8k":  # the long run is one seed's
                    lines.append(f"| {label} | {seed} | not run ||||")
                continue
            for point in curve_points(fitted):
                lines.append(f"| {label} | {seed} | {point['step']} | {point['train_seconds']:.0f} | "
                             f"{at(point, MIOU):.3f} | {at(point, 'psnr/clamped'):.2f} |")
            for what, values in (("zero-shot", zero_shot), ("fine-tuned", finals)):
                if values:
                    target = statistics.fmean(values)
                    crossed = next((p for p in curve_points(fitted) if at(p, MIOU) >= target), None)
                    crossings.append(f"{label}, seed {seed}, against GP-NeRF {what} ({target:.3f}): " + (
                        f"step {crossed['step']}, {crossed['train_seconds']:.0f} s" if crossed
                        else "never within its steps"))
    if crossings:
        lines += ["", "Where a per-scene model's per-image mIoU first reaches GP-NeRF's mean (the crossover):", ""]
        lines += [f"- {crossing}" for crossing in crossings]
    return lines


INSTANCE_KEYS = ("instance/ap_matched@0.75", "instance/ap_matched@0.5", "instance/coco_mask_ap",
                 "instance/coco_mask_ap50", "instance/coco_mask_ap75")


def instance_value(found: dict[str, Any], key: str) -> float | None:
    """``found[key]``; ``instance/ap_matched@t`` also from the per-threshold dict ``instance/ap_matched`` (``{"0.5": ...}``)."""
    if key in found:
        return found[key]
    name, _, threshold = key.partition("@")
    return found.get(name, {}).get(threshold) if threshold else None


def instance(runs: Path) -> list[str]:
    lines = ["## Instance head and DM-NeRF on layout_00 (seeds 0-2), and the connected-components baseline", "",
             "| model | seed | AP@0.75 (matched) | AP@0.5 (matched) | COCO AP | COCO AP50 | COCO AP75 "
             "| 2D reference AP@0.75 / COCO AP | train s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, prefix, read in (("instance head", "instance_l0", lambda e: e),
                                ("DM-NeRF (per scene)", "dm_nerf_l0", lambda e: e),
                                ("connected components on ID 5's classes", "cc_l0_id5",
                                 lambda e: e.get("baseline_connected_components", {}))):
        values: dict[str, list[float]] = {key: [] for key in INSTANCE_KEYS}
        reference: list[tuple[float, float]] = []
        for seed in SEEDS:
            metrics = load(runs, f"{prefix}_s{seed}")
            if metrics is None:
                lines.append(f"| {label} | {seed} | not run ||||||||")
                continue
            found = read(metrics["eval"].get(HELD, {}))
            cells = []
            for key in INSTANCE_KEYS:
                value = instance_value(found, key)
                cells.append("-" if value is None else f"{value:.3f}")
                if value is not None:
                    values[key].append(float(value))
            teacher = found.get("teacher_2d", {})
            ap, coco = instance_value(teacher, INSTANCE_KEYS[0]), teacher.get("instance/coco_mask_ap")
            if ap is not None and coco is not None:
                reference.append((float(ap), float(coco)))
                cells.append(f"{ap:.3f} / {coco:.3f}")
            else:
                cells.append("-")
            seconds = metrics.get("train", {}).get("seconds")
            lines.append(f"| {label} | {seed} | " + " | ".join(cells) + f" | {'' if seconds is None else round(seconds)} |")
        shown_reference = (f"{mean_std([a for a, _ in reference], digits=3)} / {mean_std([c for _, c in reference], digits=3)}"
                           if reference else "")
        lines.append(f"| {label} | mean +- std | " + " | ".join(mean_std(values[k], digits=3) for k in INSTANCE_KEYS)
                     + f" | {shown_reference} | |")
    return lines


FINETUNED = (("GP-NeRF (ID 5)", "id5"), ("Semantic-Ray", "semantic_ray"), ("NeuRay + semantic head", "neuray"),
             ("MVSNeRF + semantic head", "mvsnerf"), ("MVSplat", "mvsplat"), ("MVSplat + U-Net head", "mvsplat_unet"))
FEW_STEP_TARGETS = (0.70, 0.80)
"""The per-image mIoUs on the unseen layout's held-out frames the few-step table counts steps and seconds to (a
protocol whose families all start above the lower one is told apart by the higher)."""


def finetune(runs: Path, run_prefix: Callable[[str], str] = same_prefix,
             heading: str = "Fine-tuning on the unseen layout (300 steps; Table 1's fine-tuning rows)") -> list[str]:
    """Each method's runs fine-tuned on the unseen layout (300 steps, Table 1's fine-tuning rows), and the few-step
    table: the first curve point at or above each of ``FEW_STEP_TARGETS`` (steps, and seconds at the run's mean step
    time)."""
    targets = " | ".join(f"steps (s) to mIoU {target:.2f}" for target in FEW_STEP_TARGETS)
    lines = [f"## {heading}", "",
             "| method | seed | per-image mIoU at steps ... (its 6 held-out frames) | PSNR at the last step | train s "
             f"| {targets} |", "|---|---|---|---|---|" + "---|" * len(FEW_STEP_TARGETS)]
    for title, prefix in FINETUNED:
        for seed in SEEDS:
            metrics = load(runs, f"finetune_{run_prefix(prefix)}_s{seed}")
            if metrics is None:
                lines.append(f"| {title} | {seed} | not run | | |" + " |" * len(FEW_STEP_TARGETS))
                continue
            curve = sorted(metrics["finetune"]["curve"], key=lambda entry: entry["step"])
            shown = ", ".join(f"{e['step']}: {e[MIOU]:.3f}" for e in curve if e.get(MIOU) is not None)
            seconds, steps = metrics["train"]["seconds"], max(1, curve[-1]["step"])
            few = []
            for target in FEW_STEP_TARGETS:
                reached = next((e["step"] for e in curve if (e.get(MIOU) or 0) >= target), None)
                few.append("not reached" if reached is None else f"{reached} ({reached * seconds / steps:.0f})")
            lines.append(f"| {title} | {seed} | {shown} | {curve[-1].get('psnr/clamped', float('nan')):.2f} | "
                         f"{seconds:.0f} | {' | '.join(few)} |")
    return lines


def protocol_tags(runs: Path) -> list[tuple[int, str]]:
    """The protocols the ``protocol`` stage ran: ``(layout count, tag)`` of each tag with a compared family's run
    (``layouts_<tag>_<family>_s<seed>``, tag ``n<N>`` or ``n<N>_ema``: ``PROTOCOL_EMA_DECAY``, every run scored on its
    weight average)."""
    families = "|".join(prefix for _, prefix, _ in TABLE1[1:])
    pattern = re.compile(rf"layouts_(n(\d+)(?:_ema)?)_(?:{families})_s\d+")
    return sorted({(int(m.group(2)), m.group(1)) for path in runs.iterdir() if (m := pattern.fullmatch(path.name))})


def protocol(runs: Path) -> list[str]:
    """Table 1's generalization and fine-tuning rows on each generalized protocol the ``protocol`` stage ran (N training
    layouts, 150 steps each, scored over 4 unseen layouts; fine-tuned on unseen_00): the same tables, other runs."""
    lines: list[str] = []
    for count, tag in protocol_tags(runs):
        def run_prefix(prefix: str, tag: str = tag) -> str:
            return f"layouts_{tag}" if prefix == "id5" else f"layouts_{tag}_{prefix}"
        weights = "weight average (train.ema_decay)" if tag.endswith("_ema") else "last step's weights"
        where = f"{count} training layouts, {150 * count} steps, 4 unseen layouts, {weights}"
        lines += baselines(runs, run_prefix, f"The generalized protocol ({where}): Table 1's generalization rows") + [""]
        lines += finetune(runs, run_prefix, f"The generalized protocol ({where}): fine-tuned on unseen_00") + [""]
    return lines


def main(work: Path) -> int:
    runs = work / "runs"
    if not runs.is_dir():
        print(f"{runs}: no such folder; expected the WORK folder of examples/results/regenerate.sh", file=sys.stderr)
        return 2
    print("# Summary of", work, "\n")
    # A work folder's provenance, or a records folder's, one file a batch (regenerate.sh's records stage).
    for provenance in [work / "provenance.txt", *sorted((work / "provenance").glob("*.txt"))]:
        if provenance.is_file():
            print("```\n" + provenance.read_text().strip() + "\n```\n")
    for section in (table4, methods, baselines, grid, layouts, protocol, samplers, instance, finetune, per_scene):
        if lines := section(runs):
            print("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/gpnerf-results")))
