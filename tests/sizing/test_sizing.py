"""Sizing: the scene measurement's geometry, the knobs' levels, the descent and the budgets, and ``size`` end to end."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.tools.sizing.costs import StaticCost
from gpnerf_core.tools.sizing.knobs import knob_levels
from gpnerf_core.tools.sizing.options import parse_size_options, resolve_metric
from gpnerf_core.tools.sizing.scene import _seen_by, measure_scenes
from gpnerf_core.tools.sizing.search import Trial, choose, descend, describe, knob_order
from gpnerf_core.types import Frame
from pipeline_check import TINY_CLI, TINY_MODEL, TINY_SCENES, child_pids, gpnerf

# ---- the scene measurement -----------------------------------------------------------------------------------


def _frame(x: float, depth: float, height: int = 32, width: int = 48, focal: float = 24.0) -> Frame:
    """A camera at (x, 0, 0) looking down +z (OpenCV) at a plane whose depth map is ``depth`` everywhere."""
    intrinsics = torch.tensor([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1.0]])
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return Frame(rgb=torch.zeros(height, width, 3), depth=torch.full((height, width), depth),
                 semantic=torch.zeros(height, width, dtype=torch.long), intrinsics=intrinsics, c2w=c2w)


def test_a_source_shifted_by_a_quarter_of_the_view_sees_three_quarters_of_the_target():
    target = _frame(0.0, 2.0)  # 48 px at focal 24 span 4 m at depth 2
    seen = _seen_by(target.depth, target.intrinsics, target.c2w, [_frame(1.0, 2.0), _frame(0.0, 2.0)], stride=1)
    assert seen[:, 0].float().mean().item() == pytest.approx(0.75, abs=1 / 48)
    assert seen[:, 1].all()


def test_a_source_whose_depth_map_shows_a_nearer_surface_is_occluded():
    target = _frame(0.0, 2.0)
    seen = _seen_by(target.depth, target.intrinsics, target.c2w, [_frame(0.0, 1.0)], stride=2)
    assert not seen.any()


def test_the_embedded_scenes_give_bounds_around_their_depth_and_coverage_that_grows_with_sources():
    cfg = compose(["+head=unet", *TINY_MODEL, *TINY_SCENES, "dataset.frames_per_scene=8", "model.num_source_views=3"])
    components = build_components(cfg)
    scenes = components.dataset.scenes("train")
    measured = measure_scenes(components.dataset, components.view_selector, scenes=scenes, max_views=3, margin=0.2)
    assert measured.has_depth and measured.frames > 0
    assert measured.near == pytest.approx(measured.depth_low * 0.8, abs=1e-3)
    assert measured.far == pytest.approx(measured.depth_high * 1.2, abs=1e-3)
    assert 0 < measured.near < measured.depth_low < measured.depth_median < measured.depth_high < measured.far
    once = [measured.coverage[v]["1"] for v in (1, 2, 3)]
    twice = [measured.coverage[v]["2"] for v in (1, 2, 3)]
    assert once == sorted(once) and twice == sorted(twice) and twice[0] == 0.0
    assert measured.fewest_views(0.0) == 1 and measured.fewest_views(1.01) is None
    assert measured.metres_per_pixel == pytest.approx(measured.depth_median / measured.focal_px, rel=1e-3)


def test_frames_without_depth_keep_the_configured_bounds():
    cfg = compose([*TINY_MODEL, *TINY_SCENES])
    components = build_components(cfg)

    class NoDepth(type(components.dataset)):
        def load_scene(self, name):
            scene = super().load_scene(name)
            load = scene.load_frame

            def without_depth(index):
                frame = load(index)
                return Frame(frame.rgb, torch.zeros_like(frame.depth), frame.semantic, frame.intrinsics, frame.c2w)

            return type(scene)(**{**scene.__dict__, "load_frame": without_depth})

    dataset = components.dataset
    dataset.__class__ = NoDepth
    measured = measure_scenes(dataset, components.view_selector, scenes=dataset.scenes("train"), max_views=2)
    assert not measured.has_depth and measured.near is None and measured.coverage == {}


# ---- knobs, descent, budgets ---------------------------------------------------------------------------------


def test_knob_levels_shrink_from_the_reference_and_respect_the_coverage_floor():
    cfg = compose(["+head=unet", "scale=cpu"])
    levels, notes = knob_levels(cfg, min_source_views=3)
    assert levels["model.coarse_samples"] == (24, [18, 12])
    assert levels["model.fine_samples"] == (8, [4, 0])
    assert levels["model.num_source_views"] == (4, [3])
    assert levels["model.field_aggregator.width"] == (32, [24, 16])
    assert levels["model.field_aggregator.num_blocks"] == (4, [3, 2])
    assert levels["model.feature_extractor.fpn_channels"] == (16, [12, 8])
    # MVSplat's knobs and the Gaussian families' cap: another family's, each named
    assert [n.split(":")[0] for n in notes] == ["model.feature_dim", "model.depth_candidates", "model.max_gaussians"]
    without_head, notes = knob_levels(compose(["scale=cpu"]), min_source_views=4)
    assert "model.feature_extractor.fpn_channels" not in without_head and "model.num_source_views" not in without_head
    assert any("no head" in n for n in notes) and any("needs all 4" in n for n in notes)


def test_only_knobs_of_components_the_family_builds_are_sized():
    cfg = compose(["+experiment=baselines/neuray"])
    levels, notes = knob_levels(cfg, min_source_views=1)
    assert not any(key.startswith("model.field_aggregator.") for key in levels)  # NeuRay builds no GNT aggregator
    assert "model.field_aggregator.width: model 'neuray' builds no field_aggregator; not sized" in notes
    splat = compose(["+experiment=baselines/mvsplat"])
    levels, _ = knob_levels(splat, min_source_views=1)
    assert set(levels) == {"model.num_source_views", "model.depth_candidates", "model.feature_dim"}


def test_knobs_are_the_declared_fields_never_an_option_by_its_name():
    """``feature_dim`` is a knob of MVSplat's (its matching width), not of 3D Gaussian splatting's (the semantic feature
    each Gaussian carries): a knob is declared on the field it sizes (``gpnerf_core.size_knob``)."""
    from gpnerf_core.tools.sizing.knobs import configured_knobs

    assert "model.feature_dim" in {k.key for k in configured_knobs(compose(["model=mvsplat"]))}
    gaussians = compose(["+experiment=baselines/semantic_3dgs", "dataset.scenes=[layout_00]"])
    assert {k.key for k in configured_knobs(gaussians)} == {"model.num_source_views", "model.max_gaussians"}
    # A per-scene family reads no source views: its knob is its Gaussians' cap (the BudgetedStrategy budget).
    assert {k.key for k in configured_knobs(gaussians, per_scene=True)} == {"model.max_gaussians"}
    levels, notes = knob_levels(gaussians, 1, per_scene=True)
    cap = gaussians.model.max_gaussians
    assert levels == {"model.max_gaussians": (cap, sorted({max(1000, round(cap * f / 1000) * 1000)
                                                           for f in (0.5, 0.25, 0.125)}, reverse=True))}
    assert not any("num_source_views" in n for n in notes)


def _cost(changes):
    """FLOPs per ray and parameters that fall as knobs fall (a stand-in for building the model)."""
    samples, width = changes.get("model.coarse_samples", 24), changes.get("model.field_aggregator.width", 32)
    return StaticCost(parameters=1000 * width, flops_per_ray=float(samples * width * width), rays=1)


LEVELS = {"model.coarse_samples": (24, [18, 12]), "model.field_aggregator.width": (32, [24, 16])}


def _trainer(scores):
    """Trains a trial by looking its configuration up in ``scores`` (configurations absent from it fail)."""
    def train(trial):
        key = describe(trial.changes)
        if key not in scores:
            trial.error = "diverged"
            return
        trial.accuracy = scores[key]
        trial.measured = {"seconds_per_frame": trial.cost.flops_per_ray / 1e4, "peak_memory_mb": 500.0}

    return train


def test_the_descent_keeps_levels_within_tolerance_and_builds_on_them():
    scores = {"the reference": 0.70, "transformer width 24": 0.69, "transformer width 16": 0.60,
              "transformer width 24, coarse samples 18": 0.685, "transformer width 24, coarse samples 12": 0.675}
    order = knob_order(LEVELS, _cost)
    assert order == ["model.field_aggregator.width", "model.coarse_samples"]  # width 24 saves more FLOPs than 18 samples
    trials = descend(LEVELS, order, _cost, _trainer(scores), tolerance=0.02)
    assert [(t.name, t.kept) for t in trials] == [
        ("reference", True), ("transformer width 24", True), ("transformer width 16", False),
        ("coarse samples 18", True), ("coarse samples 12", False),
    ]
    chosen, failure = choose(trials, {})
    assert failure is None and chosen.changes == {"model.field_aggregator.width": 24, "model.coarse_samples": 18}


def test_a_failed_trial_ends_its_knob_and_a_failed_reference_raises():
    from gpnerf_core.tools.sizing.search import ReferenceFailed

    trials = descend(LEVELS, list(LEVELS), _cost, _trainer({"the reference": 0.7}), tolerance=0.02)
    assert [t.name for t in trials] == ["reference", "coarse samples 18", "transformer width 24"]
    assert all(t.error == "diverged" and not t.kept for t in trials[1:])
    with pytest.raises(ReferenceFailed):
        descend(LEVELS, list(LEVELS), _cost, _trainer({}), tolerance=0.02)


def test_budgets_pick_the_cheapest_fitting_trial_or_name_the_constraint_that_failed():
    trials = [Trial("reference", {}, _cost({}), accuracy=0.7, kept=True),
              Trial("w24", {"model.field_aggregator.width": 24}, _cost({"model.field_aggregator.width": 24}), accuracy=0.69,
                    kept=True),
              Trial("w16", {"model.field_aggregator.width": 16}, _cost({"model.field_aggregator.width": 16}), accuracy=0.5)]
    for trial in trials:
        trial.measured = {"seconds_per_frame": trial.cost.flops_per_ray / 1e4, "peak_memory_mb": 500.0}
    chosen, _ = choose(trials, {"max_parameters": 30_000})
    assert chosen.name == "w24"
    chosen, failure = choose(trials, {"max_parameters": 20_000, "max_memory_mb": 1000})
    assert chosen is None
    assert failure.startswith("size.max_parameters=20000: no configuration within the tolerance meets it")
    assert "the least within tolerance is 24,000" in failure and "max_memory_mb" not in failure


def test_size_options_are_checked_one_line_each():
    options, overrides = parse_size_options(["+head=unet", "size.steps=50", "size.knobs=[fine_samples,model.coarse_samples]",
                                             "size.max_parameters=2e6"])
    assert overrides == ["+head=unet"] and options.steps == 50 and options.budgets() == {"max_parameters": 2e6}
    assert options.knobs == ["model.fine_samples", "model.coarse_samples"]
    for bad, expected in (("size.step=5", "unknown size option; known: size.out, size.steps"),
                          ("size.steps=-1", "size.steps='-1': expected an integer >= 0"),
                          ("size.tolerance=nan", "size.tolerance='nan': expected a number >= 0"),
                          ("size.metric=ap", "size.metric='ap': expected one of miou, ap75, psnr"),
                          ("size.knobs=[depth]", "size.knobs: unknown knob 'depth'")):
        with pytest.raises(ConfigError, match=expected.replace("[", r"\[").replace("(", r"\(")):
            parse_size_options([bad])
    with pytest.raises(ConfigError, match="size.metric=miou needs a model with class scores"):
        resolve_metric(parse_size_options(["size.metric=miou"])[0], None)
    assert resolve_metric(parse_size_options([])[0], None) == ("psnr", 0.5)
    # The default metric is that of what the model predicts (label rendering included: no head needed).
    assert resolve_metric(parse_size_options([])[0], "classes") == ("miou", 0.02)
    assert resolve_metric(parse_size_options([])[0], "instances") == ("ap75", 0.02)
    with pytest.raises(ConfigError, match="size.metric=miou needs a model with class scores .* use size.metric=ap75"):
        resolve_metric(parse_size_options(["size.metric=miou"])[0], "instances")


# ---- the command ---------------------------------------------------------------------------------------------


SIZE = ["+head=unet", "+loss=dgs", *TINY_CLI, "model.feature_extractor.fpn_channels=8", "size.steps=2"]


@pytest.fixture(scope="module")
def sized(tmp_path_factory):
    folder = tmp_path_factory.mktemp("size")
    result = gpnerf("size", *SIZE, "size.knobs=[semantic_width]", f"size.out={folder / 'out'}", cwd=folder)
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-3000:]
    return folder, result


def test_size_writes_its_report_chart_and_a_config_that_run_accepts(sized):
    folder, result = sized
    out = folder / "out"
    report = json.loads((out / "size.json").read_text())
    names = [t["name"] for t in report["trials"]]
    assert names == ["reference", "semantic width 4"]  # one knob, one level below the reference: two trials
    assert report["chosen"] and report["scene"]["has_depth"]
    for name in ("size.md", "speed_accuracy.png", "speed_accuracy.csv", "scene.json", "experiment/sized.yaml"):
        assert (out / name).is_file(), name
    assert "FLOPs per ray (millions) mean" in (out / "speed_accuracy.csv").read_text()
    sized_yaml = (out / "experiment" / "sized.yaml").read_text()
    assert sized_yaml.startswith("# @package _global_") and f"near: {report['scene']['near']}" in sized_yaml
    command = report["command"]
    assert "+experiment=sized" in command and f"hydra.searchpath=[file://{out.resolve()}]" in command
    args = [a.strip("'") for a in command.split()[3:]]
    run = gpnerf(*args, "train.steps=1", f"out_dir={folder / 'sized_run'}", cwd=folder)
    assert run.returncode == 0, run.stderr[-3000:]
    config = (folder / "sized_run" / "config.yaml").read_text()
    assert f"near: {report['scene']['near']}" in config
    evaluated = gpnerf("eval", f"checkpoint={next((folder / 'sized_run' / 'checkpoints').glob('*.pt'))}",
                       f"out_dir={folder / 'sized_eval'}", cwd=folder)
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]  # the checkpoint keeps the search path


def test_size_again_with_the_same_request_reuses_its_runs_and_refuses_another_request(sized):
    folder, _ = sized
    again = gpnerf("size", *SIZE, "size.knobs=[semantic_width]", f"size.out={folder / 'out'}", cwd=folder)
    assert again.returncode == 0 and "steps ..." not in again.stdout  # no trial trained again
    other = gpnerf("size", *SIZE, "size.tolerance=0.5", f"size.out={folder / 'out'}", cwd=folder)
    assert other.returncode == 2 and "holds a sizing of another request" in other.stderr


def test_a_knob_of_a_component_the_family_never_builds_is_refused_before_training(tmp_path):
    tiny = [o for o in TINY_CLI if not o.startswith(("model.coarse", "model.fine", "model.field_aggregator."))]
    result = gpnerf("size", "+experiment=baselines/neuray", *tiny, "size.steps=2",
                    "size.knobs=[model.field_aggregator.width]", f"size.out={tmp_path / 'out'}", cwd=tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    assert ("size.knobs names model.field_aggregator.width, which cannot be sized for model 'neuray': model 'neuray' builds "
            "no field_aggregator; not sized") in result.stderr
    assert not (tmp_path / "out" / "runs").exists()


def test_a_budget_no_reachable_configuration_meets_is_refused_before_training(tmp_path):
    result = gpnerf("size", *SIZE, "size.max_parameters=1000", f"size.out={tmp_path / 'out'}", cwd=tmp_path)
    assert result.returncode == 2
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("error: size.max_parameters=1000: no configuration the search can reach meets it")
    assert not (tmp_path / "out" / "runs").exists()
    assert not (tmp_path / "out" / "request.json").exists()  # so the corrected request may use the folder


def test_sigterm_stops_the_sizing_and_the_trial_it_is_training(tmp_path):
    import signal
    import time

    env = dict(os.environ, GPNERF_CACHE=str(tmp_path / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    process = subprocess.Popen([sys.executable, "-m", "gpnerf_core", "size", *SIZE, "size.steps=100000",
                                f"size.out={tmp_path / 'out'}"], cwd=tmp_path, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    trials = []
    deadline = time.monotonic() + 300
    while not trials and time.monotonic() < deadline and process.poll() is None:
        trials = child_pids(process.pid)
        time.sleep(0.2)
    assert trials, "no trial started"
    time.sleep(1.0)
    process.send_signal(signal.SIGTERM)
    stderr = process.communicate(timeout=120)[1]
    assert process.returncode == 143 and "Traceback" not in stderr, stderr[-2000:]
    assert stderr.strip().splitlines()[-1].startswith("interrupted (SIGTERM): size stopped")
    time.sleep(0.5)
    assert not [pid for pid in trials if Path(f"/proc/{pid}").exists()], "a trial outlived the sizing"



def test_a_level_that_cannot_be_built_is_passed_over_not_ending_its_knob():
    def cost_of(changes):
        if changes.get("model.field_aggregator.width") == 24:
            raise ConfigError("semantic width 64 is not a multiple of the view attention's 24 channels")
        return _cost(changes)

    scores = {"the reference": 0.70, "transformer width 16": 0.69, "transformer width 16, coarse samples 18": 0.60}
    order = knob_order(LEVELS, cost_of)
    assert order == ["model.field_aggregator.width", "model.coarse_samples"]  # ranked by width 16, its first buildable level
    trials = descend(LEVELS, order, cost_of, _trainer(scores), tolerance=0.02)
    assert [(t.name, t.kept) for t in trials] == [
        ("reference", True), ("transformer width 24", False), ("transformer width 16", True),
        ("coarse samples 18", False),
    ]
    assert trials[1].error.startswith("cannot be built: semantic width 64") and trials[1].accuracy is None
    assert choose(trials, {})[0].changes == {"model.field_aggregator.width": 16}


PER_SCENE = ["+experiment=baselines/semantic_3dgs", "dataset.scenes=[layout_00]", "dataset.height=32", "dataset.width=48",
             "dataset.frames_per_scene=9", "dataset.eval_every=3", "threads=1"]


def test_a_rasterizing_family_refuses_a_flop_budget_in_one_line(tmp_path):
    result = gpnerf("size", *PER_SCENE, "size.max_flops_per_ray=1e6", f"size.out={tmp_path / 's'}", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith(
        "error: size.max_flops_per_ray=1e+06: model 'semantic_3dgs' rasterizes Gaussians with numba kernels")


def test_a_per_scene_family_is_sized_by_its_gaussians_cap_scored_by_its_predictions_counted_as_trained(tmp_path):
    """semantic_3dgs: no source views measured or sized, mIoU by its label rendering (no head), the Gaussians' cap
    turned down, each trial's parameters those it trained to (Gaussians included), FLOPs n/a."""
    out = tmp_path / "s"
    result = gpnerf("size", *PER_SCENE, "train.steps=4", "model.max_gaussians=2000", f"size.out={out}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "sizing 1 knob(s) in this order: Gaussians" in result.stdout and "keep while miou" in result.stdout
    report = json.loads((out / "size.json").read_text())
    trials = report["trials"]
    assert [t["changes"] for t in trials] == [{}, {"model.max_gaussians": 1000}]
    for trial in trials:
        run = json.loads((Path(trial["runs"][0]) / "metrics.json").read_text())
        assert trial["parameters"] == run["parameters"]["total"] and run["parameters"]["gaussians"] > 0
        assert trial["flops_per_ray"] is None
    assert "n/a" in (out / "size.md").read_text()


def test_a_per_scene_family_without_a_size_knob_is_refused_in_one_line(tmp_path, monkeypatch):
    from gpnerf_core.commands import size

    monkeypatch.setattr(size, "configured_knobs", lambda cfg, registry=None, per_scene=False: [])
    with pytest.raises(ConfigError, match=r"^size: model 'semantic_3dgs' \(per-scene\) declares no size knob"):
        size.main([*PER_SCENE, f"size.out={tmp_path / 's'}"])
    assert not (tmp_path / "s").exists()  # refused before anything is written
