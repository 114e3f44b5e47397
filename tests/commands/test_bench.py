"""The bench command measures, prints and writes figures (never asserts speed); its bad input is one line."""

import json
import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf
import torch

from gpnerf_core.errors import ConfigError

TINY = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "threads=1",
]


def bench(*args, cwd):
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", GPNERF_CACHE=str(cwd / "cache"))
    return subprocess.run([sys.executable, "-m", "gpnerf_core", "bench", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def test_bench_measures_both_variants_and_writes_bench_json(tmp_path):
    result = bench("size=demo", "repeats=2", "warmup=0", "families=neuray", *TINY, "model.fine_samples=2",
                   f"out_dir={tmp_path / 'b'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "b" / "bench.json").read_text())
    assert report["matmul_peak_gflops"] > 0
    demo = report["sizes"]["demo"]
    for variant in ("gpnerf", "gnt_only"):
        train, render = demo[variant]["train"], demo[variant]["render"]
        assert len(train["seconds"]) == 2 and train["rays"] == 16 and train["flops"] > 0
        assert render["rays"] == 16 * 24 and render["peak_memory_mb"] > 0  # the 32x48 view at stride 2
    # The GP-NeRF model has the semantic parts the anchor lacks, and does more work per ray.
    assert {"head", "semantic"} <= set(demo["gpnerf"]["train"]["parameters"])
    assert not {"head", "semantic"} & set(demo["gnt_only"]["train"]["parameters"])
    assert demo["gpnerf"]["train"]["flops"] > demo["gnt_only"]["train"]["flops"]
    assert set(demo["ratios"]) == {"train_step_time", "train_peak_memory", "train_flops", "render_samples_per_second",
                                   "render_frame_time"}
    assert demo["ratios"]["train_flops"] == demo["gpnerf"]["train"]["flops"] / demo["gnt_only"]["train"]["flops"]
    assert "GP-NeRF / GNT-only (min)" in result.stdout
    # A compared family is measured on the same images, views and rays, and set beside GP-NeRF in the same run.
    neuray = demo["neuray"]
    assert "+experiment=baselines/neuray" in neuray["overrides"] and neuray["train"]["rays"] == 16
    assert neuray["render"]["rays"] == 16 * 24 and {"depth_init", "coarse"} <= set(neuray["train"]["parameters"])
    assert demo["family_ratios"]["neuray"]["train_flops"] == neuray["train"]["flops"] / demo["gpnerf"]["train"]["flops"]
    assert "neuray / GP-NeRF (min)" in result.stdout


def test_bench_bad_input_is_one_line(tmp_path):
    unknown = bench("size=huge", cwd=tmp_path)
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == "error: bench size='huge' is unknown; known sizes: demo, small, paper"
    family = bench("families=nerf", cwd=tmp_path)
    assert family.returncode == 2 and family.stderr.strip().startswith("error: bench families='nerf': expected some of ")
    assert "semantic_ray" in family.stderr and "gnt" not in family.stderr.split("of ", 1)[1]
    bad = bench("repeats=0", cwd=tmp_path)
    assert bad.returncode == 2 and bad.stderr.strip() == "error: bench repeats=0: expected an integer >= 1"
    cuda = bench("device=cuda", cwd=tmp_path)
    if not __import__("torch").cuda.is_available():
        assert cuda.returncode == 2 and "CUDA is not available" in cuda.stderr and cuda.stderr.count("\n") == 1


def test_another_family_in_the_overrides_is_refused_naming_it_and_families(tmp_path):
    """Issue 55: ``bench size=demo model=neuray`` ended in Hydra's "Could not override
    model.semantic_field.enabled", a key of the GNT-only anchor bench adds itself."""
    from gpnerf_core.tools.bench.sizes import check_family_overrides

    with pytest.raises(ConfigError, match=r"^bench model=neuray: bench measures GP-NeRF \(model=gnt\) and its "
                                          r"GNT-only anchor, .* with families=neuray \(drop model=neuray\)$"):
        check_family_overrides(["model=neuray"])
    with pytest.raises(ConfigError, match=r"^bench \+experiment=baselines/semantic_ray: .*families=semantic_ray"):
        check_family_overrides(["+experiment=baselines/semantic_ray", "train.rays=16"])
    check_family_overrides(["model=gnt", "+experiment=table4_id5", "train.rays=16"])  # GP-NeRF's own: measured
    refused = bench("size=demo", "model=neuray", *TINY, cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr.strip().startswith("error: bench model=neuray: ")
    assert "Could not override" not in refused.stderr and not (tmp_path / "outputs").exists()


def profile(*args, cwd):
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", GPNERF_CACHE=str(cwd / "cache"))
    return subprocess.run([sys.executable, "-m", "gpnerf_core.tools.bench.profile", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def test_profile_prints_the_step_its_operators_and_its_stages(tmp_path):
    result = profile("size=demo", "variant=gpnerf", "rows=5", *TINY, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("one profiled training step: ")
    operators, by_stage = result.stdout.split("\none profiled step by stage")
    table = [line for line in operators.splitlines()[1:] if line.strip() and not line.startswith("---")]
    assert len(table) == 1 + 5 + 1 and "aten::" in operators  # header, five operators, the total
    stages = {line.split("|")[0].strip(): line for line in by_stage.splitlines()[3:]}
    for name in ("encode sources", "encode target (teacher)", "transformers", "semantic field", "head",
                 "loss", "optimizer", "all"):
        assert name in stages, by_stage
    forward, backward, total = (float(x) for x in stages["transformers"].split("|")[1].split()[:5:2])
    assert backward > 0 and total == pytest.approx(forward + backward, abs=2e-3)
    render = profile("size=demo", "variant=gpnerf", "phase=render", "rows=3", *TINY, cwd=tmp_path)
    assert render.returncode == 0, render.stderr
    assert render.stdout.startswith("one profiled rendered view: ")
    stages = {line.split("|")[0].strip(): line for line in render.stdout.split("by stage")[1].splitlines()[3:]}
    assert {"encode sources", "projection", "transformers", "semantic field", "head"} <= set(stages)
    assert "optimizer" not in stages and float(stages["transformers"].split("|")[1].split()[2]) == 0.0  # no backward
    unknown = profile("variant=rgb", cwd=tmp_path)
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == "error: variant='rgb' is unknown; known variants: gpnerf, gnt_only, both"


def test_stage_times_charge_backward_to_the_stage_whose_forward_made_it():
    from torch.profiler import profile as torch_profile

    from gpnerf_core.runtime.profiling import GRADIENT_ACCUMULATION, stage, stage_times

    weights = torch.randn(512, 512, requires_grad=True)  # ~1 GFLOP: far above the profiler's own ~4 ms a stage
    with torch_profile() as profiler:
        with stage("heavy"):
            hidden = torch.tanh(torch.randn(2048, 512) @ weights @ weights)
        with stage("light"):
            loss = hidden.sum()
        loss.backward()
    times = stage_times(profiler.events())
    assert set(times) >= {"heavy", "light", GRADIENT_ACCUMULATION}
    assert times["heavy"].backward > 0 and times["heavy"].backward > times["light"].backward
    assert times["light"].forward > 0 and times["heavy"].forward > times["light"].forward


def test_sweep_slopes_rows_and_chart(tmp_path):
    """The fitted slope is the log-log least-squares slope; rows carry every cost; the chart is a PNG."""
    from gpnerf_core.tools.bench.sweeps import SWEEPS, draw, fitted_slope, rows_of, slopes

    assert fitted_slope([64, 128, 256], [1.0, 2.0, 4.0]) == pytest.approx(1.0)
    assert fitted_slope([2, 4, 8], [3.0, 12.0, 48.0]) == pytest.approx(2.0)
    assert fitted_slope([2], [1.0]) is None and fitted_slope([2, 4], [0.0, 1.0]) is None
    sweep = SWEEPS["views"]
    measured = {
        variant: [{"train": {"seconds_min": 0.1 * x * scale, "peak_memory_mb": 100.0 + x},
                   "render": {"seconds_min": 0.2 * x * scale, "peak_memory_mb": 50.0}} for x, _ in sweep.points]
        for variant, scale in (("gpnerf", 2.0), ("gnt_only", 1.0))
    }
    measured["gnt_only"][1]["render"] = {"error": "out of memory"}
    rows = rows_of(sweep, measured)
    assert len(rows) == 2 * len(sweep.points) and rows[0]["training step (s)"] == pytest.approx(0.4)
    assert rows[len(sweep.points) + 1]["rendering a view (s)"] is None and "out of memory" in rows[6]["error"]
    fitted = slopes(sweep, rows)
    assert fitted["gpnerf"]["training step (s)"] == pytest.approx(1.0)
    assert fitted["gnt_only"]["rendering peak memory (MiB)"] == pytest.approx(0.0, abs=1e-9)
    draw(sweep, rows, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_unknown_sweep_lists_the_known_ones(tmp_path):
    result = bench("sweep=pixels", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == "error: bench sweep='pixels' is unknown; known sweeps: rays, views, samples, image"


def test_every_family_composes_at_every_size_with_its_images_and_rays():
    """Every family composes at each size, on the size's images, views and rays: the size's scale sizes each family and
    part by its own preset (was: ``bench size=demo families=mvsnerf`` refused by scale=cpu's resunet_fpn keys)."""
    from gpnerf_core.config.compose import compose
    from gpnerf_core.tools.bench.sizes import SIZES, baseline_families, variant_overrides

    assert "semantic_nerf_grid" in baseline_families()  # its family through the experiment it includes
    for size in SIZES.values():
        reference = compose(variant_overrides(size, "gpnerf", []))
        for family in baseline_families():
            cfg = compose(variant_overrides(size, family, []))
            same = [(key, OmegaConf.select(cfg, key), OmegaConf.select(reference, key))
                    for key in ("train.rays", "dataset.height", "dataset.width")]
            assert all(a == b for _, a, b in same), (size.name, family, same)


def test_bench_takes_baseline_experiments_and_registered_families():
    from gpnerf_core.tools.bench.sizes import SIZES, checked_families, variant_overrides

    assert checked_families("mvsplat,semantic_ray") == ["mvsplat", "semantic_ray"]
    with pytest.raises(ConfigError, match="the baseline experiments, the registered model families and the project's"):
        checked_families("mini")
    assert "+experiment=baselines/mvsplat" in variant_overrides(SIZES["demo"], "mvsplat", [])
    # the project's own experiment (GP-NeRF's instance head): on the size's images and rays, without its semantic head
    instance = variant_overrides(SIZES["demo"], "instance", [])
    assert "+experiment=instance" in instance and "+head=unet" not in instance


def test_a_per_scene_family_is_measured_with_its_preset_its_gaussians_and_no_flop_figure(tmp_path):
    """semantic_3dgs beside GP-NeRF on GP-NeRF's tiny overrides: those it has no field for (samples, source views) are
    left out for it with a note; it is initialised (its Gaussians counted), evaluated on its scene's held-out frames,
    and its FLOPs (the rasterizer's numba kernels, which torch's counter cannot see) are n/a, never 0."""
    result = bench("size=demo", "repeats=1", "warmup=0", "phases=train", "families=semantic_3dgs", *TINY,
                   f"out_dir={tmp_path / 'b'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    notes = [line for line in result.stderr.splitlines() if line.startswith("bench: note: semantic_3dgs")]
    assert len(notes) == 1 and "model.coarse_samples=6" in notes[0] and "model.num_source_views=2" in notes[0]
    family = json.loads((tmp_path / "b" / "bench.json").read_text())["sizes"]["demo"]["semantic_3dgs"]
    assert "+experiment=baselines/semantic_3dgs" in family["overrides"] and "eval.splits=[train]" in family["overrides"]
    assert "model.coarse_samples=6" not in family["overrides"]
    train = family["train"]
    assert train["parameters"]["gaussians"] > 0 and train["flops"] is None and train["flops_torch_only"] >= 0
    assert "numba" in train["flops_note"]
    row = next(line for line in result.stdout.splitlines() if line.split()[1:2] == ["semantic_3dgs"])
    assert row.split()[-2:] == ["n/a", "n/a"] and "0.000" not in row  # phases=train: no render cells
    assert "x0.00" not in result.stdout and "note: semantic_3dgs: FLOPs n/a" in result.stdout


def test_a_failed_measurement_is_one_line_on_stderr_and_exit_1(tmp_path):
    result = bench("size=demo", "repeats=1", "warmup=0", "phases=train", *TINY, "model.num_source_views=5",
                   f"out_dir={tmp_path / 'b'}", cwd=tmp_path)
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: bench: demo gpnerf train failed: ") and "model.num_source_views" in last
    assert last.endswith("(1 more in bench.json)")


def test_a_registered_family_without_preset_gets_the_loss_of_what_it_predicts():
    from gpnerf_core.tools.bench.sizes import SIZES, family_loss, loss_options

    base = (*SIZES["demo"].common, "model=semantic_3dgs")  # no preset: model= alone
    assert family_loss(base, "semantic_3dgs") == "image" and loss_options(base) == ()


def test_bench_refine_times_the_gaussian_step_at_each_thread_count_in_one_run(tmp_path):
    """``bench refine=<count>``: the per-scene Gaussian family's step from the unseen layout's depth points at that
    count, each thread count's steps and parts in bench.json with the CPU model; no timing is asserted."""
    result = bench("refine=300", "refine_threads=1,2", "repeats=2", "warmup=1", "dataset.height=32",
                   "dataset.width=48", f"out_dir={tmp_path / 'r'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "r" / "bench.json").read_text())
    refine = report["refine"]
    assert refine["gaussians"] == {"start": 300, "end": 300, "steps": 6} and refine["image"] == [32, 48]
    assert set(refine["threads"]) == {"1", "2"} and report["machine"]["cpu_model"]
    for entry in refine["threads"].values():
        assert len(entry["seconds"]) == 2
        assert set(entry["parts_median"]) == {"forward", "backward", "density", "optimizer", "checks"}
    assert "model.init_points=300" in report["overrides"] and "forward ms" in result.stdout


def test_bench_refine_bad_counts_are_one_line(tmp_path):
    zero = bench("refine=0", cwd=tmp_path)
    assert zero.returncode == 2 and zero.stderr.strip() == "error: bench refine=0: expected an integer >= 1"
    threads = bench("refine=100", "refine_threads=two", cwd=tmp_path)
    assert threads.returncode == 2 and threads.stderr.strip().startswith("error: bench refine_threads='two'")
