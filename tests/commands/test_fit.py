"""``fit``: one scene's per-scene Gaussian model fitted until a stop rule says it has enough, its curve recorded."""

import json
import math

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.engine.fit_start import FitStart
from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase
from gpnerf_core.training.stopping import StopRules, Stopper, lower_is_better
from pipeline_check import TINY_MODEL, TINY_SCENES, in_process, make_trainer

SPLATS = [*TINY_SCENES, "dataset.scenes=[layout_00]", "model.init_points=300", "model.feature_dim=4",
          "model.sh_degree=1", "threads=1", "eval.save_images=0", "eval.max_views_per_scene=1"]
"""A tiny fit of embedded ``layout_00`` (the default +experiment=baselines/semantic_3dgs), one held-out frame."""


def stop_of(rules: StopRules, values: list[float | None], every: int = 100):
    """Feed ``values`` as the evaluations at steps 0, every, 2 every, ...; the first stop (or None)."""
    stopper = Stopper(rules)
    for index, value in enumerate(values):
        decision = stopper.observe(index * every, value)
        if decision is not None:
            return decision
    return None


def test_the_stopper_says_when_and_why():
    plateau = StopRules(patience=3, min_delta=0.005)
    decision = stop_of(plateau, [0.5, 0.9, 0.912, 0.914, 0.915, 0.916, 0.99])
    assert (decision.reason, decision.step) == ("plateau", 500)  # 0.914, 0.915, 0.916: none 0.005 above 0.912
    assert decision.said == "plateau (no gain of 0.005 in 3 evaluations; best 0.912 at step 200)"
    assert stop_of(plateau, [0.5, 0.6, 0.7, 0.8]) is None
    assert stop_of(StopRules(patience=1), [0.5, 0.5]).step == 100  # equal is no gain, even with min_delta 0
    assert stop_of(StopRules(patience=1, min_delta=0.0), [0.5, 0.5]).step == 100
    assert stop_of(StopRules(patience=2), [0.5, None, None]).reason == "plateau"  # not scored: no gain
    target = stop_of(StopRules(target=0.8, patience=2), [0.1, 0.85])
    assert (target.reason, target.step) == ("target", 100) and "0.850 >= 0.8" in target.said
    assert stop_of(StopRules(target=0.1), [0.2]).step == 0  # reached at the start
    lower = StopRules(metric="depth/abs_rel", target=0.05, patience=1)
    assert lower_is_better("depth/abs_rel") and not lower_is_better("psnr/clamped")
    assert stop_of(lower, [0.3, 0.2, 0.04]).reason == "target" and stop_of(lower, [0.3, 0.31]).reason == "plateau"
    assert stop_of(StopRules(), [0.1, 0.1, 0.1]) is None  # no rule: only the step budget ends the fit
    stopper = Stopper(StopRules(seconds=2.0))
    assert stopper.spent(5, 1.99) is None
    spent = stopper.spent(6, 2.01)
    assert (spent.reason, spent.step) == ("seconds", 6) and stopper.observe(7, 0.0) is spent  # the first stop holds
    with pytest.raises(ConfigError, match=r"fit.seconds=-1.0: expected a finite training-seconds budget >= 0"):
        StopRules(seconds=-1.0)
    with pytest.raises(ConfigError, match="fit.target=nan"):
        StopRules(target=math.nan)


def test_a_callback_ends_training_cleanly_at_its_step(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, "train.steps=5"])
    trainer = make_trainer(cfg, tmp_path)

    def stop_at_two(state):
        if state.steps_done == 2:
            state.request_stop("enough")

    result = trainer.fit(progress=False, callbacks=[TrainingCallback(TrainingPhase.AFTER_STEP, stop_at_two,
                                                                     timed=False)])
    assert (result.steps, result.stopped, trainer.step) == (2, "enough", 2)
    assert result.checkpoint.name == "step_0000002.pt" and result.history[-1]["step"] == 2.0
    assert torch.load(result.checkpoint, weights_only=False)["step"] == 2
    again = trainer.fit(progress=False)  # a later fit goes on to train.steps: the stop was this fit's
    assert (again.steps, again.stopped) == (5, None)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("fit")


def fitted(work, name, *overrides, base=SPLATS):
    """``fit`` with ``base`` and ``overrides`` into ``work/name``: its exit code, metrics and curve file (None where
    missing)."""
    out = work / name
    code = in_process("fit", *base, f"dataset.root={work / 'scenes'}", *overrides, f"out_dir={out}")
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else None
    curve = json.loads((out / "fit_curve.json").read_text()) if (out / "fit_curve.json").is_file() else None
    return code, metrics, curve


def test_a_plateau_stops_the_fit_and_the_curve_is_recorded(work, capsys):
    code, metrics, curve = fitted(work, "plateau", "train.steps=6", "fit.eval_every=2", "fit.patience=1",
                                  "fit.min_delta=0.9")
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    fit = metrics["fit"]
    assert fit["scene"] == "layout_00" and fit["curve"] == curve and [p["step"] for p in curve] == [0, 2]
    assert fit["start"] == {"kind": "points", "checkpoint": None, "gaussians": 300, "seconds": 0.0, "notes": []}
    assert fit["stopped"]["reason"] == "plateau" and fit["stopped"]["step"] == 2 == metrics["train"]["steps"]
    assert fit["stopped"]["said"].startswith("plateau (no gain of 0.9 in 1 evaluation; best ")
    first, last = curve
    assert set(first) == {"step", "train_seconds", "seconds", "gaussians", "miou/image_mean_present", "miou/dataset",
                          "psnr/clamped"}
    assert first["train_seconds"] == first["seconds"] == 0.0 and first["gaussians"] == 300
    assert last["seconds"] == last["train_seconds"] > 0 and last["gaussians"] > 0
    held_out = metrics["eval"]["train_heldout"]  # the last point is the run's own final evaluation
    assert last["miou/image_mean_present"] == held_out["miou/image_mean_present"]
    assert (work / "plateau" / "checkpoints" / "step_0000002.pt").is_file()
    assert "fit: stopped at step 2 after " in err and ": plateau (no gain of 0.9 in 1 evaluation; best " in err
    assert in_process("report", str(work / "plateau")) == 0  # report reads a fit like any run


def test_the_step_budget_target_and_seconds_stop_the_fit(work, capsys):
    code, metrics, curve = fitted(work, "steps", "train.steps=3", "fit.eval_every=2")
    assert code == 0, capsys.readouterr().err[-2000:]
    assert [p["step"] for p in curve] == [0, 2, 3] and metrics["fit"]["stopped"]["reason"] == "steps"
    assert metrics["fit"]["stopped"]["said"] == "steps (train.steps=3 reached)"

    code, metrics, curve = fitted(work, "target", "train.steps=4", "fit.target=0.0")
    assert code == 0, capsys.readouterr().err[-2000:]
    stopped = metrics["fit"]["stopped"]
    assert (stopped["reason"], stopped["step"], metrics["train"]["steps"]) == ("target", 0, 0)
    assert [p["step"] for p in curve] == [0] and (work / "target" / "checkpoints" / "step_0000000.pt").is_file()

    code, metrics, curve = fitted(work, "seconds", "train.steps=4", "fit.seconds=1e-6", "fit.eval_every=0")
    assert code == 0, capsys.readouterr().err[-2000:]
    assert metrics["fit"]["stopped"]["reason"] == "seconds" and [p["step"] for p in curve] == [0, 1]


def test_a_checkpoint_start_is_asked_of_starting_point(work, monkeypatch, capsys):
    import gpnerf_core.commands.fit as fit_command

    checkpoint = work / "generalizable.pt"
    checkpoint.write_bytes(b"not read here")
    asked = []

    def starting_point(cfg, path, dist):
        asked.append((path, int(cfg.fit.start_every)))
        return FitStart(kind="checkpoint", checkpoint=str(path), seconds=1.5, notes=("a start note",),
                        overrides=("model.feature_dim=6", "model.sh_degree=0"))

    monkeypatch.setattr(fit_command, "starting_point", starting_point)
    code, metrics, curve = fitted(work, "started", f"checkpoint={checkpoint}", "train.steps=1", "fit.start_every=2")
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    assert asked == [(checkpoint, 2)] and "note: a start note" in err
    start = metrics["fit"]["start"]
    assert (start["kind"], start["checkpoint"], start["seconds"], start["notes"]) == (
        "checkpoint", str(checkpoint), 1.5, ["a start note"])
    assert curve[0]["seconds"] == 1.5 and curve[-1]["seconds"] == round(1.5 + curve[-1]["train_seconds"], 2)
    config = (work / "started" / "config.yaml").read_text()  # the start's overrides composed after the command's
    assert "feature_dim: 6" in config and "sh_degree: 0" in config and "init_points: 300" in config


@pytest.mark.parametrize("overrides, message", [
    (["dataset.num_train_scenes=2", "dataset.scenes=[layout_00,layout_01]"],
     r"fit fits one scene: expected 'dataset.scenes=\[<one scene>\]'; dataset.scenes gives 2: layout_00, layout_01"),
    (["train.steps=0"], r"train.steps=0: expected an integer >= 1"),
    (["fit.seconds=-1"], r"fit.seconds=-1.0: expected null \(no budget\) or a finite training-seconds budget > 0"),
    (["fit.seconds=0"], r"fit.seconds=0.0: expected null \(no budget\) or a finite training-seconds budget > 0"),
    (["fit.seconds=inf"], r"fit.seconds=inf: expected null \(no budget\) or a finite training-seconds budget"),
    (["fit.eval_every=0", "fit.patience=2"], r"fit.patience=2: a stop rule on the held-out metric needs evaluations "
                                              r"while fitting, but fit.eval_every=0"),
    (["fit.eval_every=0", "fit.target=0.5"], r"fit.target=0.5: .* fit.eval_every=0"),
    (["fit.start_opacity=1.5"], r"fit.start_opacity=1.5: expected an opacity in \(0, 1\)"),
    (["fit.start_tolerance=1.5"], r"fit.start_tolerance=1.5: expected a relative depth tolerance in \(0, 1\)"),
    (["fit.start_conflicts=-1"], r"fit.start_conflicts=-1: expected an integer >= 0"),
    (["fit.start_geometry=depth"], r"fit.start_geometry='depth': expected predicted or points"),
    (["dataset.eval_every=0", "fit.patience=2"], r"eval.splits=\[train\] select no frame of dataset 'embedded'"),
    (["fit.metric=miou/nope", "train.steps=2"], r"fit.metric=miou/nope: the evaluation of the held-out frames of "
                                                r"scene 'layout_00' gives no such value; expected one of: .*psnr/clamped"),
    (["checkpoint=/nowhere/gen.pt"], r"checkpoint=/nowhere/gen.pt: no such file; expected a generalizable run's"),
])
def test_bad_input_is_refused_in_one_line_before_the_run_folder(work, capsys, overrides, message):
    import re

    code, _, _ = fitted(work, "refused", *overrides)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and re.search(message, err[-1]), err[-3:]
    assert not (work / "refused").exists()


def test_a_model_that_is_not_a_per_scene_gaussian_family_is_refused(work, capsys):
    code, _, _ = fitted(work, "refused", "+experiment=baselines/semantic_nerf", base=SPLATS[:7])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: fit: model.name=semantic_nerf is not a per-scene Gaussian family; "
                                            "expected one of "), err[-3:]
    assert "semantic_3dgs" in err[-1] and not (work / "refused").exists()


def test_a_resumed_fit_keeps_its_points_and_ends_as_the_uninterrupted_one(work, capsys):
    import shutil

    steps = ["train.steps=4", "fit.eval_every=2", "train.checkpoint_every=2"]
    code, whole, _ = fitted(work, "whole", *steps)
    assert code == 0, capsys.readouterr().err[-2000:]
    shutil.copytree(work / "whole", work / "cut")  # as if interrupted after the checkpoint at step 2
    (work / "cut" / "checkpoints" / "step_0000004.pt").unlink()
    (work / "cut" / "metrics.json").unlink()
    code, resumed, curve = fitted(work, "cut", *steps, "train.resume=auto")
    assert code == 0, capsys.readouterr().err[-2000:]

    def kept(points):
        return [{key: value for key, value in point.items() if "seconds" not in key} for point in points]

    assert [p["step"] for p in curve] == [0, 2, 4] and kept(curve) == kept(whole["fit"]["curve"])
    assert resumed["fit"]["stopped"]["reason"] == "steps" and resumed["fit"]["start"] == whole["fit"]["start"]


def test_a_metric_a_scene_without_labels_does_not_score_is_refused_where_a_rule_reads_it():
    from gpnerf_core.evaluation.curves import check_fit_metric

    held_out = {"miou/image_mean_present": None, "psnr/clamped": 21.0, "count/images": 2,
                "labels/unavailable_reason": "scene 'room' has no labels", "timing": {"seconds_per_frame": 0.1}}
    check_fit_metric("psnr/clamped", held_out, True, "room")
    check_fit_metric("miou/image_mean_present", held_out, False, "room")  # recorded on the curve, read by no rule
    with pytest.raises(ConfigError, match=r"^fit.metric=miou/image_mean_present: the held-out frames of scene 'room' "
                                          r"give no value of it \(scene 'room' has no labels\), so fit.target and "
                                          r"fit.patience cannot read it; expected .* fit.metric=psnr/clamped$"):
        check_fit_metric("miou/image_mean_present", held_out, True, "room")
    with pytest.raises(ConfigError, match=r"gives no such value; expected one of: count/images, psnr/clamped$"):
        check_fit_metric("timing", held_out, False, "room")


def test_a_generalizable_checkpoint_starts_the_fit(work, capsys):
    from pipeline_check import TINY_CLI

    base = work / "gpnerf"
    assert in_process("run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=2", "dataset.scenes=[layout_00]",
                      f"dataset.root={work / 'scenes'}", f"out_dir={base}") == 0, capsys.readouterr().err[-2000:]
    checkpoint = base / "checkpoints" / "step_0000002.pt"
    code, metrics, curve = fitted(work, "from_gpnerf", f"checkpoint={checkpoint}", "train.steps=1",
                                  "fit.eval_every=0")
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    start = metrics["fit"]["start"]
    assert start["kind"] == "checkpoint" and start["checkpoint"] == str(checkpoint) and start["seconds"] > 0
    assert start["gaussians"] > 0 and curve[0]["seconds"] == round(start["seconds"], 2)
    assert any("the start: " in note and "model 'gnt'" in note for note in start["notes"])
    config = (work / "from_gpnerf" / "config.yaml").read_text()
    assert "feature_stride: " in config and "name: unet" in config  # GP-NeRF's head carried with its features
    assert "opacity_reset_every: 1000000000" in config  # a started fit keeps the start's opacities
    # the scene's own points with GP-NeRF's semantics: the family's schedule kept, its head carried
    code, metrics, _ = fitted(work, "points_gpnerf", f"checkpoint={checkpoint}", "train.steps=1", "fit.eval_every=0",
                              "fit.start_geometry=points")
    assert code == 0, capsys.readouterr().err[-2000:]
    start = metrics["fit"]["start"]
    assert any("the start: " in note and "Gaussians at the scene's depth with the semantics model 'gnt'" in note
               for note in start["notes"]), start["notes"]
    config = (work / "points_gpnerf" / "config.yaml").read_text()
    assert "name: unet" in config and "opacity_reset_every: 1000000000" not in config
    code, _, _ = fitted(work, "points_nothing", f"checkpoint={checkpoint}", "fit.start_geometry=points",
                        "fit.start_semantics=false")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: fit.start_geometry=points with fit.start_semantics=false takes "
                                            "nothing from the checkpoint"), err[-3:]
    # a per-scene checkpoint starts nothing: refused naming its family
    per_scene = sorted((work / "from_gpnerf" / "checkpoints").glob("*.pt"))[-1]
    code, _, _ = fitted(work, "from_per_scene", f"checkpoint={per_scene}", "train.steps=1")
    assert code == 2 and "model=semantic_3dgs is a per-scene family" in capsys.readouterr().err


def test_the_handoff_tool_measures_a_start_frame_by_frame(work, monkeypatch, capsys):
    from gpnerf_core.tools import start_handoff

    checkpoint = work / "gpnerf" / "checkpoints" / "step_0000002.pt"  # test_a_generalizable_checkpoint_starts_the_fit's
    if not checkpoint.is_file():
        pytest.skip("needs the tiny GP-NeRF run of test_a_generalizable_checkpoint_starts_the_fit (same module)")
    monkeypatch.setattr("sys.argv", ["start_handoff", "--checkpoint", str(checkpoint), "--frames", "1", "--threads", "1",
                                     "--min-views", "0", *TINY_SCENES, "dataset.scenes=[layout_00]",
                                     f"dataset.root={work / 'scenes'}"])
    assert start_handoff.main() == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("start: ") and "of model 'gnt', scene 'layout_00'" in out[0]
    row = out[2].split(" | ")
    assert len(row) == 6 and all(math.isfinite(float(value)) for value in row[1:4])  # PSNRs and coverage
