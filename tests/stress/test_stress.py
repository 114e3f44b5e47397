"""The stress suite: its cases, the summary's failure rule, the CLI, and defined outputs under degenerate geometry."""

import json
import math
from dataclasses import replace

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import NonFiniteError
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.interfaces import StressCase
from gpnerf_core.registry.plugins import PluginInfo, make_plugin_manager
from gpnerf_core.registry.components import collect, get_registry
from gpnerf_core.tools.stress.runner import Outcome
from gpnerf_core.tools.stress.summary import StressSummary
from gpnerf_core import hookimpl
from gpnerf_plugins.stress.geometry_cases import Baseline, OneWrongCamera, random_rotations
from gpnerf_plugins.stress.image_cases import Blur, Exposure, GaussianNoise, Jpeg, blur
from gpnerf_plugins.stress.target_cases import ViewDistance, distance_to_training
from pipeline_check import TINY_CLI as TINY
from pipeline_check import TINY_MODEL, TINY_SCENES, gpnerf

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny trained run (3 steps) in a folder of its own, with its scene cache."""
    folder = tmp_path_factory.mktemp("stress")
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, "train.steps=3", f"out_dir={folder / 'run'}", cwd=folder)
    assert result.returncode == 0, result.stderr[-2000:]
    return folder


# ---- the suite from the command line ---------------------------------------------------------------------------------


def test_quick_suite_runs_every_case_and_writes_tables_plots_and_reasons(trained):
    out = trained / "quick"
    result = gpnerf("stress", str(trained / "run"), "--quick", "--threads", "1", "--out", str(out), cwd=trained)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "stress.json").read_text())
    registered = set(get_registry().stress_cases)
    assert set(summary["cases"]) == registered
    outcomes = summary["outcomes"]
    evaluated = [o for o in outcomes if not o["skipped"]]
    assert all(not o["non_finite"] and math.isfinite(o["metrics"]["miou"]) for o in evaluated)
    by_case = {o["case"]: o for o in outcomes}
    assert by_case["textureless"]["skipped"] is None  # the flat-colour variant was rendered and evaluated
    # Three disjoint thirds of 2 source views need 6 candidates; this scene has 4 training frames.
    assert "three disjoint thirds" in by_case["baseline"]["skipped"]
    table = (out / "stress.md").read_text()
    assert "### wrong_camera" in table and "fails at" in table and "Skipped: a target has" in table
    assert (out / "source_views.png").stat().st_size > 0 and "clean" in (out / "stress.csv").read_text()
    again = gpnerf("stress", str(trained / "run"), "--quick", "--out", str(out), cwd=trained)
    assert again.returncode == 2 and "already holds a stress suite's results" in again.stderr


def test_unknown_case_lists_the_known_ones(trained):
    result = gpnerf("stress", str(trained / "run"), "--cases", "fog", "--out", str(trained / "x"), cwd=trained)
    assert result.returncode == 2
    assert "unknown stress case 'fog'; known cases: source_views, baseline" in result.stderr
    assert not (trained / "x").exists()


def test_no_runs_is_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    result = gpnerf("stress", str(tmp_path / "empty"), "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert result.returncode == 2 and "no trained runs or checkpoints under" in result.stderr


class PoisonedImages(StressCase):
    name = "poisoned_images"
    description = "source images full of NaN"
    levels = (1.0,)

    def perturb_sources(self, level, sources, generator):
        return replace(sources, rgb=torch.full_like(sources.rgb, float("nan")))


def test_a_case_giving_non_finite_metrics_fails_the_suite_after_writing_it(trained, monkeypatch):
    from gpnerf_core.commands.stress import main

    monkeypatch.setenv("GPNERF_CACHE", str(trained / "cache"))
    monkeypatch.setitem(get_registry().stress_cases, "poisoned_images", (PoisonedImages(), "test"))
    out = trained / "poisoned"
    expected = r"1 evaluation\(s\) gave non-finite metrics; first: run poisoned_images 1: .*NaN"
    with pytest.raises(NonFiniteError, match=expected):
        main([str(trained / "run"), "--cases", "poisoned_images", "--quick", "--out", str(out)])
    outcome = json.loads((out / "stress.json").read_text())["outcomes"][1]
    assert outcome["case"] == "poisoned_images" and "input images that were not finite already" in outcome["error"]
    assert "| NOT FINITE |" in (out / "stress.md").read_text() and outcome["non_finite"]


# ---- registration ----------------------------------------------------------------------------------------------------


def test_third_party_cases_register_and_bad_ones_are_reported():
    class NoLevels(StressCase):
        name = "no_levels"

    class Fine(StressCase):
        name = "fine_case"
        levels = (1.0, 2.0)

    plugin = type("plugin", (), {})()

    @hookimpl
    def gpnerf_register_stress_cases():
        return [Fine(), NoLevels(), "not a case", Fine()]

    plugin.gpnerf_register_stress_cases = gpnerf_register_stress_cases
    loaded = make_plugin_manager(builtins=(), autoload=False)
    loaded.register(plugin, PluginInfo("third", "third-dist", "1.0"))
    registry = collect(loaded)
    assert list(registry.stress_cases) == []  # a name registered twice is never picked silently
    problems = [str(p) for p in registry.problems]
    assert any("stress/no_levels rejected: levels ()" in p for p in problems)
    assert any("is not a StressCase instance" in p for p in problems)
    assert any("stress/fine_case rejected: stress case 'fine_case' is registered 2 times by third (third-dist 1.0)"
               in p for p in problems)


# ---- the cases -------------------------------------------------------------------------------------------------------


def test_random_rotations_turn_by_exactly_the_level():
    rotations = random_rotations(16, 5.0, torch.Generator().manual_seed(0))
    angles = torch.rad2deg(torch.arccos(((rotations.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert torch.allclose(angles, torch.full((16,), 5.0, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(rotations @ rotations.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(16, 3, 3))


@pytest.fixture()
def scene_and_sources(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                   "dataset.frames_per_scene=12", "dataset.eval_every=4"])
    components = build_components(cfg)
    frames = FrameCache(components.dataset, torch.device("cpu"))
    scene = frames.scene(components.dataset.scenes("train")[0])
    target = scene.eval_frames[0]
    return components, frames, scene, target, frames.source_views(scene, list(scene.train_frames[:2]))


def test_baseline_thirds_are_ordered_by_distance_and_never_take_the_target(scene_and_sources):
    _, _, scene, target, _ = scene_and_sources
    case = Baseline()
    assert case.unavailable(3.0, {}, [scene], 2) is None
    distance = {}
    for level in case.levels:
        picked = case.source_indices(level, scene, target, 2, lambda *a: [])
        assert len(picked) == 2 and target not in picked and set(picked) <= set(scene.train_frames)
        distance[level] = float((scene.c2w[picked, :3, 3] - scene.c2w[target, :3, 3]).norm(dim=-1).mean())
    assert distance[1.0] < distance[2.0] < distance[3.0]


def test_view_distance_thirds_are_held_out_frames_ordered_by_distance_to_the_training_cameras(scene_and_sources):
    _, _, scene, _, _ = scene_and_sources
    case = ViewDistance()
    assert case.unavailable(3.0, {}, [scene], 2) is None and len(scene.eval_frames) == 3
    distance = {}
    for level in case.levels:
        picked = case.target_frames(level, scene, scene.eval_frames)
        assert picked and set(picked) <= set(scene.eval_frames)
        distance[level] = float(distance_to_training(scene, picked).mean())
    assert distance[1.0] <= distance[2.0] <= distance[3.0] and distance[1.0] < distance[3.0]
    assert "three thirds by distance need 3" in case.unavailable(1.0, {}, [replace(scene, eval_frames=[0, 1])], 2)


def test_a_case_choosing_a_frame_that_is_not_held_out_is_refused_naming_it(scene_and_sources):
    from gpnerf_core.errors import DataError
    from gpnerf_core.evaluation.evaluator import _targets

    components, frames, scene, _, _ = scene_and_sources
    cfg = compose(["+head=unet", *TINY_MODEL, *TINY_SCENES, "dataset.frames_per_scene=12", "dataset.eval_every=4"])
    kept = _targets(cfg, components, frames, "train", lambda s: list(s.eval_frames[-1:]))
    assert [index for _, index in kept] == list(scene.eval_frames[-1:])
    with pytest.raises(DataError, match=f"target frame {scene.train_frames[0]} is not a held-out frame"):
        _targets(cfg, components, frames, "train", lambda s: [s.train_frames[0]])


def test_perturbations_are_reproducible_and_stay_in_range(scene_and_sources):
    *_, sources = scene_and_sources
    for case in (GaussianNoise(), Blur(), Jpeg(), Exposure(), OneWrongCamera()):
        for level in case.levels:
            a = case.perturb_sources(level, sources, torch.Generator().manual_seed(1))
            b = case.perturb_sources(level, sources, torch.Generator().manual_seed(1))
            assert torch.equal(a.rgb, b.rgb) and torch.equal(a.c2w, b.c2w), case.name
            assert a.rgb.shape == sources.rgb.shape and 0 <= float(a.rgb.min()) and float(a.rgb.max()) <= 1
    moved = OneWrongCamera().perturb_sources(90.0, sources, torch.Generator().manual_seed(1))
    assert not torch.equal(moved.c2w[0], sources.c2w[0]) and torch.equal(moved.c2w[1:], sources.c2w[1:])
    assert float((moved.c2w[0, :3, 3] - sources.c2w[0, :3, 3]).norm()) == pytest.approx(0.5, abs=1e-5)


def test_blur_keeps_a_constant_image_and_its_mean():
    constant = torch.full((1, 3, 16, 20), 0.4)
    assert torch.allclose(blur(constant, 2.0), constant, atol=1e-6)
    noise = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    blurred = blur(noise, 1.0)
    assert blurred.std() < noise.std() and abs(float(blurred.mean() - noise.mean())) < 0.01


# ---- defined outputs under degenerate geometry (documented in docs/architecture.md) ---------------------------------


def _assert_finite(model, camera, sources):
    prediction = model.predict(camera, sources, stride=0, chunk_rays=256)
    for name in ("rgb", "depth", "semantic", "logits"):
        value = getattr(prediction, name)
        assert value is not None and bool(torch.isfinite(value).all()), name
    return prediction


def test_rays_no_source_view_sees_and_samples_behind_every_camera_give_finite_outputs(scene_and_sources):
    components, frames, scene, target, sources = scene_and_sources
    model = components.model.eval()
    camera = frames.camera(scene, frames.frame(scene, target))
    flipped = sources.c2w.clone()
    flipped[:, :3, :3] = flipped[:, :3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0]))  # every sample behind
    _assert_finite(model, camera, replace(sources, c2w=flipped))
    away = sources.c2w.clone()
    away[:, :3, 3] += 1000.0  # no sample projects into any source image: every sample invalid
    _assert_finite(model, camera, replace(sources, c2w=away))
    one = replace(sources, rgb=sources.rgb[:1], intrinsics=sources.intrinsics[:1], c2w=sources.c2w[:1])
    _assert_finite(model, camera, one)


# ---- the summary -----------------------------------------------------------------------------------------------------


def _outcome(method, seed, case, level, miou, psnr=20.0, label=None):
    return Outcome(f"{method}_{seed}", method, seed, case, level, label or ("clean" if level is None else f"{level:g}"),
                   {"miou": miou, "psnr": psnr})


def test_failure_rule_and_least_degraded_method():
    outcomes = []
    for seed in (0, 1):
        outcomes += [
            _outcome("a", seed, "clean", None, 0.6), _outcome("a", seed, "blur", 1.0, 0.5),
            _outcome("a", seed, "blur", 2.0, 0.29),
            _outcome("b", seed, "clean", None, 0.4), _outcome("b", seed, "blur", 1.0, 0.38),
            _outcome("b", seed, "blur", 2.0, 0.3),
        ]
    summary = StressSummary(outcomes)
    assert summary.failure("a", "blur") == "2" and summary.failure("b", "blur") == "holds"
    assert summary.retained("a", "blur") == pytest.approx((0.5 / 0.6 + 0.29 / 0.6) / 2)
    assert summary.least_degraded("blur")[0] == "b"
    assert summary.best_at_most_severe("blur") == ("b", "2", pytest.approx(0.3))
    assert "Highest at the most severe level (2): b (30.00)." in summary.markdown()
    assert "| a | mIoU x100 | 60.00 ± 0.00 | 50.00 ± 0.00 | 29.00 ± 0.00 | 2 |" in summary.markdown()


def test_models_without_semantics_fail_on_psnr():
    outcomes = [Outcome("r", "rgb", 0, "clean", None, "clean", {"psnr": 24.0}),
                Outcome("r", "rgb", 0, "jpeg", 20.0, "20", {"psnr": 19.0}),
                Outcome("r", "rgb", 0, "jpeg", 8.0, "8", {"psnr": 17.5})]
    assert StressSummary(outcomes).failure("rgb", "jpeg") == "8"


def test_instance_models_fail_on_ap75_and_the_csv_has_its_column():
    outcomes = [Outcome("g", "grouping", 0, "clean", None, "clean", {"ap75": 0.8, "psnr": 24.0}),
                Outcome("g", "grouping", 0, "view_distance", 1.0, "near", {"ap75": 0.7, "psnr": 10.0}),
                Outcome("g", "grouping", 0, "view_distance", 3.0, "far", {"ap75": 0.3, "psnr": 23.0})]
    summary = StressSummary(outcomes)
    assert summary.metric_of("grouping") == "ap75" and summary.failure("grouping", "view_distance") == "far"
    assert "| grouping | AP@0.75 x100 | 80.00 | 70.00 | 30.00 | far |" in summary.markdown()
    assert summary.csv().splitlines()[0].split(",")[6:10] == ["miou", "accuracy", "ap75", "psnr"]


def test_a_per_scene_model_gets_the_cases_that_apply_and_a_note_when_none_does(tmp_path):
    run = gpnerf("run", "+experiment=baselines/semantic_3dgs", "dataset.scenes=[layout_00]", "dataset.height=32",
                 "dataset.width=48", "dataset.frames_per_scene=9", "dataset.eval_every=3", "train.steps=2", "threads=1",
                 "eval.save_images=0", f"out_dir={tmp_path / 'run'}", cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    out = tmp_path / "suite"
    result = gpnerf("stress", str(tmp_path / "run"), "--cases", "view_distance,blur", "--threads", "1", "--out",
                    str(out), cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    outcomes = json.loads((out / "stress.json").read_text())["outcomes"]
    by_level = {(o["case"], o["label"]): o for o in outcomes}
    for label in ("near", "medium", "far"):  # one held-out frame per third: each scored on its own
        assert by_level[("view_distance", label)]["skipped"] is None
        assert math.isfinite(by_level[("view_distance", label)]["metrics"]["miou"])
    assert "no source views to change" in by_level[("blur", "2")]["skipped"]
    assert "stress: note" not in result.stderr
    none = gpnerf("stress", str(tmp_path / "run"), "--cases", "blur", "--quick", "--threads", "1", "--out",
                  str(tmp_path / "none"), cwd=tmp_path)
    assert none.returncode == 0, none.stderr[-3000:]
    notes = [line for line in none.stderr.splitlines() if line.startswith("stress: note")]
    assert len(notes) == 1 and "per-scene" in notes[0] and "--cases view_distance" in notes[0]


def test_merge_summarises_suites_run_apart(trained):
    runs = []
    for name in ("a", "b"):
        out = trained / f"part_{name}"
        result = gpnerf("stress", str(trained / "run"), "--quick", "--cases", "blur,jpeg", "--out", str(out),
                        cwd=trained)
        assert result.returncode == 0, result.stderr[-2000:]
        runs.append(out)
    merged = gpnerf("stress", "--merge", *map(str, runs), "--out", str(trained / "merged"), cwd=trained)
    assert merged.returncode == 0, merged.stderr[-2000:]
    summary = json.loads((trained / "merged" / "stress.json").read_text())
    assert len(summary["outcomes"]) == 6 and set(summary["cases"]) == {"blur", "jpeg"}
    # The same model twice: two values per cell, no spread (evaluation is deterministic).
    assert "± 0.00" in (trained / "merged" / "stress.md").read_text()


def test_merge_of_a_folder_without_results_is_one_line(tmp_path):
    from gpnerf_core.errors import DataError
    from gpnerf_core.commands.stress import main

    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"--merge .*empty: no stress.json \(expected the --out folder"):
        main(["--merge", str(tmp_path / "empty"), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_an_interrupted_suite_keeps_what_finished_and_a_copied_run_is_never_evaluated_with_another_checkpoint(trained):
    import os
    import shutil
    import signal
    import subprocess
    import sys
    import time

    copy = trained / "copied_run"
    shutil.copytree(trained / "run", copy, ignore=shutil.ignore_patterns("checkpoints"))
    skipped = gpnerf("stress", str(copy), "--quick", "--out", str(trained / "copied"), cwd=trained)
    assert skipped.returncode == 2 and "no checkpoint in" in skipped.stderr  # not the original's checkpoint

    out = trained / "interrupted"
    env = dict(os.environ, GPNERF_CACHE=str(trained / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    process = subprocess.Popen(
        [sys.executable, "-m", "gpnerf_core", "stress", str(trained / "run"), "--quick", "--threads", "1",
         "--out", str(out)], cwd=trained, env=env, stderr=subprocess.PIPE, text=True)
    lines = []
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        line = process.stderr.readline()
        lines.append(line)
        if line.startswith("stress: run ") and " clean" not in line:  # the clean condition and one level finished
            break
    process.send_signal(signal.SIGTERM)
    rest = process.communicate(timeout=120)[1]
    assert process.returncode == 143, "".join(lines) + rest
    assert rest.strip().splitlines()[-1].startswith("interrupted (SIGTERM): stress stopped")
    assert "Traceback" not in rest
    saved = json.loads((out / "stress.json").read_text())
    assert saved["interrupted"] == "SIGTERM" and len(saved["outcomes"]) >= 2
