"""Per-scene semantic 3D Gaussian splatting (``model=semantic_3dgs``): where the Gaussians start, densification and
pruning with the optimizer's moments following the rows, a model whose size changes resumed bit for bit after a kill
and built at its checkpoint's size by every command, and its refusals (no points, an inconsistent checkpoint, NaN in a
parameter, the size cap, a weight average)."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest
import torch

from gpnerf_core import (
    DataError, DefaultStrategy, NonFiniteError, ScenePoints, TrainingState, neighbour_scales, reset_opacity,
    resize_parameter, scene_extent, starting_points,
)
from gpnerf_core.cli import main as cli_main
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.build import build_components
from gpnerf_core.model.weights import load_weights
from gpnerf_core.registry.components import get_registry
from gpnerf_core.testing.inputs import kit_parts, model_scene
from gpnerf_core.training.optimizer import make_optimizer
from pipeline_check import KIT_PARTS, TINY_SCENES, make_trainer
from ply_reader import read_ply

SMALL = {"name": "semantic_3dgs", "init_points": 300, "feature_dim": 4, "sh_degree": 1, "schedule_steps": 2000}
"""A small model (the contract kit sets its density schedule itself, ``KIT_DENSITY``: densifying at its 2nd and 4th
step, no opacity reset, as the kit's synthetic scene has cameras 0.1 m apart and 3DGS's world-size pruning at 0.1 x
that extent would remove every Gaussian after one)."""
TINY = [*TINY_SCENES, "dataset.scenes=[layout_00]", "model.init_points=400", "model.feature_dim=4",
        "model.sh_degree=1", "model.schedule_steps=6", "model.densify_from=1", "model.densify_every=2",
        "model.densify_until=5", "model.opacity_reset_every=4", "model.sh_degree_every=2", "train.log_every=1",
        "threads=1", "eval.save_images=0"]
"""A 6-step fit of one 32 x 48 layout whose schedule clones, splits, prunes and resets opacity within the steps."""


def small_model(head: bool = False):
    return get_registry().build("model", dict(SMALL),
                                parts=kit_parts(get_registry(), "semantic_3dgs", head=head, parts=KIT_PARTS))


def test_resize_parameter_carries_the_moments_of_kept_rows_and_starts_new_ones_at_zero():
    old = torch.nn.Parameter(torch.arange(8.0).reshape(4, 2))
    optimizer = torch.optim.Adam([{"params": [old], "lr": 0.1, "name": "rows"}])
    old.grad = torch.ones(4, 2)
    optimizer.step()
    moments = optimizer.state[old]["exp_avg"].clone()
    kept = torch.tensor([True, False, True, False])
    values = torch.cat([old.detach()[kept], torch.full((3, 2), 7.0)])
    new = resize_parameter(optimizer, old, values, kept)
    assert optimizer.param_groups[0]["params"] == [new] and old not in optimizer.state
    state = optimizer.state[new]
    assert torch.equal(state["exp_avg"][:2], moments[kept]) and torch.equal(state["exp_avg"][2:], torch.zeros(3, 2))
    assert state["exp_avg_sq"].shape == (5, 2) and int(state["step"]) == 1
    new.grad = torch.ones(5, 2)
    optimizer.step()  # the optimizer steps the new tensor with its state
    with pytest.raises(ValueError, match="only the first dimension may change"):
        resize_parameter(optimizer, new, torch.zeros(5, 3))


def test_the_gaussians_start_from_sparse_points_else_from_depth_else_the_scene_is_refused():
    scene = model_scene()
    sparse = ScenePoints(xyz=torch.rand(50, 3) + torch.tensor([0.0, 0.0, 2.0]), rgb=torch.rand(50, 3))
    points, origin = starting_points(dataclasses.replace(scene, sparse_points=lambda: sparse), 40, 1)
    assert origin == "sparse points" and points.count == 40
    assert all(any(torch.equal(p, q) for q in sparse.xyz) for p in points.xyz[:5])  # a subset of them
    points, origin = starting_points(scene, 10_000, 4)
    assert origin == "depth" and points.count == 2 * 8 * 12  # two training frames, every 4th pixel
    frame = scene.load_frame(0)  # the first point is pixel (0, 0) of frame 0 at its depth
    k = frame.intrinsics
    z = frame.depth[0, 0]
    assert torch.allclose(points.xyz[0], torch.stack([(0 - k[0, 2]) / k[0, 0] * z, (0 - k[1, 2]) / k[1, 1] * z, z])
                          + frame.c2w[:3, 3], atol=1e-5)
    assert scene_extent(scene) == pytest.approx(0.11)  # 1.1 x the cameras' largest distance from their mean

    def without_depth(index):
        return dataclasses.replace(scene.load_frame(index), depth=torch.zeros(32, 48))

    bare = dataclasses.replace(scene, load_frame=without_depth)
    with pytest.raises(DataError, match=r"scene 'kit' has no sparse points .* and no depth in its training frames; "
                                        r"a per-scene Gaussian model starts"):
        starting_points(bare, 100, 1)


def test_sparse_points_in_another_frame_than_the_poses_are_named():
    """Points none of which any training camera sees (another COLMAP model's frame): refused naming them and why,
    where before every Gaussian started invisible and the model ended with none, the cause unnamed."""
    scene = model_scene()
    behind = ScenePoints(xyz=torch.rand(50, 3) - torch.tensor([0.0, 0.0, 3.0]), rgb=torch.rand(50, 3))
    with pytest.raises(DataError, match=r"^scene 'kit': none of its 50 sparse points \(a capture's ply_file_path, "
                                        r"sparse_points.ply\) lies in front of a training camera inside its image: "
                                        r"the points are in another frame than the poses"):
        starting_points(dataclasses.replace(scene, sparse_points=lambda: behind), 40, 1)
    aside = ScenePoints(xyz=torch.rand(50, 3) + torch.tensor([100.0, 0.0, 2.0]), rgb=torch.rand(50, 3))
    with pytest.raises(DataError, match="none of its 50 sparse points"):
        starting_points(dataclasses.replace(scene, sparse_points=lambda: aside), 40, 1)


def test_a_depth_stride_too_coarse_for_any_valid_depth_names_the_key_and_a_stride_that_works():
    scene = model_scene()

    def corner_empty(index):  # only pixel (0, 0) of a stride over the image: make it invalid
        frame = scene.load_frame(index)
        depth = frame.depth.clone()
        depth[0, 0] = 0.0
        return dataclasses.replace(frame, depth=depth)

    sparse = dataclasses.replace(scene, load_frame=corner_empty)
    with pytest.raises(DataError, match=r"^scene 'kit': model.init_depth_stride=64 meets no valid depth in its training "
                                        r"frames \(32x48: .*\); expected a finer stride: model.init_depth_stride=47 "
                                        r"meets some$"):
        starting_points(sparse, 100, 64)
    assert starting_points(sparse, 100, 47)[0].count == 2  # the stride it names works


def test_prune_opacity_of_one_is_refused_and_pruning_every_gaussian_names_its_cause():
    with pytest.raises(ConfigError, match=r"^model.prune_opacity=1.0: expected a finite number in \[0, 1\) \(Gaussians whose "
                                          r"opacity is below it are pruned"):
        get_registry().build("model", {**SMALL, "prune_opacity": 1.0},
                             parts=kit_parts(get_registry(), "semantic_3dgs", head=False, parts=KIT_PARTS))
    torch.manual_seed(0)
    model, optimizer = _fitted_field()
    field = model.gaussians
    strategy = DefaultStrategy(prune_opacity=0.99)  # above every Gaussian's opacity (0.1 at the start)
    with pytest.raises(ConfigError, match=r"^step 119: density control would prune every one of the \d+ Gaussians "
                                          r"\(\d+ with opacity below model.prune_opacity=0.99 \(the largest opacity "
                                          r"is .*\)\), leaving the model with no Gaussians; expected .*lower "
                                          r"model.prune_opacity"):
        strategy.densify_and_prune(field, optimizer, 120, prune_large=False)
    assert field.size > 0  # refused before anything was removed


@pytest.mark.parametrize("key, value, message", [
    ("sh_degree", 4, r"^model.sh_degree=4: expected an integer in \[0, 3\] \(3D Gaussian splatting's degrees\)$"),
    ("sh_degree", -1, r"^model.sh_degree=-1: expected an integer in \[0, 3\]"),
    ("sh_degree", 10, r"^model.sh_degree=10: expected an integer in \[0, 3\]"),
    ("init_opacity", 1.0, r"^model.init_opacity=1.0: expected a finite number in \(0, 1\) \(stored as its logit"),
    ("init_opacity", 0.0, r"^model.init_opacity=0.0: expected a finite number in \(0, 1\)"),
])
def test_colour_degree_and_opacities_out_of_range_name_the_key_and_the_range(key, value, message):
    with pytest.raises(ConfigError, match=message):
        get_registry().build("model", {**SMALL, key: value},
                             parts=kit_parts(get_registry(), "semantic_3dgs", head=False, parts=KIT_PARTS))


def test_mvsplat_sh_degree_out_of_range_names_the_key():
    with pytest.raises(ConfigError, match=r"^model.sh_degree=10: expected an integer in \[0, 4\]"):
        get_registry().build("model", {"name": "mvsplat", "sh_degree": 10},
                             parts=kit_parts(get_registry(), "mvsplat", head=False, parts=KIT_PARTS))


@pytest.mark.parametrize("degree", [10, -1, 2])
def test_a_checkpoint_with_a_corrupt_active_degree_is_refused_naming_the_file_and_key(degree):
    """SMALL has sh_degree 1: 2 is as corrupt as 10 for it (was: 'spherical-harmonic degree 10', naming nothing)."""
    model = small_model()
    model.hooks.initialise(model_scene())
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    weights["gaussians.active_degree"] = torch.tensor(degree)
    with pytest.raises(DataError, match=rf"^checkpoint bad.pt: gaussians.active_degree={degree}: expected the "
                                        r"colour's active spherical-harmonic degree, an integer in \[0, 1\] "
                                        r"\(model.sh_degree=1\)"):
        load_weights(small_model(), weights, "checkpoint bad.pt")


def test_a_checkpoint_with_no_gaussians_is_named_when_it_renders():
    model = small_model()
    weights = {k: v.clone() for k, v in model.state_dict().items()}  # never initialised: count 0
    fresh = small_model()
    load_weights(fresh, weights, "checkpoint empty.pt")
    from gpnerf_core.testing.inputs import model_view
    camera, _ = model_view(sources=False)
    with pytest.raises(DataError, match=r"^checkpoint empty.pt: it holds 0 Gaussians \(gaussians.count=0\), so "
                                        r"model=semantic_3dgs has nothing to render"):
        fresh.render(camera, 1, channels=False)
    with pytest.raises(ConfigError, match="has no Gaussians: it is fitted on its scene first"):
        small_model().render(camera, 1, channels=False)


def test_a_starting_scale_is_the_rms_distance_to_the_three_nearest_neighbours():
    grid = torch.stack(torch.meshgrid(torch.arange(5.0), torch.arange(5.0), indexing="ij"), -1).reshape(-1, 2)
    xyz = torch.cat([grid * 0.1, torch.zeros(25, 1)], dim=1)
    scales = neighbour_scales(xyz)
    assert scales[12] == pytest.approx(0.1)  # the centre: four neighbours at 0.1
    assert scales[0] == pytest.approx(((0.01 + 0.01 + 0.02) / 3) ** 0.5)  # a corner: 0.1, 0.1, 0.1 sqrt 2


def _fitted_field():
    model = small_model()
    model.hooks.initialise(model_scene())
    optimizer = make_optimizer(model, {"means": 1.0, "harmonics": 1.0, "harmonics_rest": 1.0, "opacities": 1.0,
                                       "scales": 1.0, "rotations": 1.0, "features": 1.0, "head": 1.0},
                               model.hooks.optimizer_options(10))
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    optimizer.step()
    return model, optimizer


def test_densification_clones_small_splits_large_prunes_transparent_and_the_moments_follow():
    torch.manual_seed(0)
    model, optimizer = _fitted_field()
    field = model.gaussians
    count = field.size
    with torch.no_grad():
        field.log_scales[:] = np.log(0.001)
        field.log_scales[1] = np.log(0.5)  # large: split
        field.opacity_logits[2] = -10.0  # transparent: pruned
    field.gradient_sum[:2] = 1.0  # Gaussians 0 (small: cloned) and 1 (large: split) are over the threshold
    field.gradient_count[:] = 1
    means_before = field.means.detach().clone()
    moments = optimizer.state[field.means]["exp_avg"].clone()
    strategy = DefaultStrategy(grad_threshold=0.5, percent_dense=0.01, prune_opacity=0.005, prune_screen_radius=20.0,
                               prune_world_scale=100.0, max_gaussians=10_000)
    added, removed = strategy.densify_and_prune(field, optimizer, 1, prune_large=False)
    assert field.size == count + 1 + 1 - 1 and (added, removed) == (2, 1)  # +clone, +2 -1 split, -1 pruned
    assert torch.equal(field.means[0], means_before[0]) and torch.equal(field.means[count - 2], means_before[0])
    halves = field.log_scales[-2:].exp()
    assert torch.allclose(halves, torch.full_like(halves, 0.5 / 1.6))  # the split pair, scales / (0.8 x 2)
    assert not any(torch.equal(row, means_before[1]) for row in field.means)  # the split original is gone
    state = optimizer.state[field.means]
    assert state["exp_avg"].shape == (field.size, 3) and torch.equal(state["exp_avg"][0], moments[0])
    assert torch.equal(state["exp_avg"][-2:], torch.zeros(2, 3))  # new rows start with zero moments
    assert int(field.count) == field.size and field.gradient_sum.abs().sum() == 0  # statistics start again
    for name, parameter in field.rows().items():
        assert parameter.shape[0] == field.size and any(parameter is p for g in optimizer.param_groups
                                                        for p in g["params"]), name
    reset_opacity(field, optimizer)
    assert float(torch.sigmoid(field.opacity_logits.detach()).max()) <= 0.01 + 1e-6
    assert torch.equal(optimizer.state[field.opacity_logits]["exp_avg"], torch.zeros(field.size))


def test_the_size_cap_stops_growth_and_is_said_once(caplog):
    torch.manual_seed(0)
    model, optimizer = _fitted_field()
    field = model.gaussians
    field.gradient_sum[:] = 1.0
    field.gradient_count[:] = 1
    strategy = DefaultStrategy(grad_threshold=0.5, percent_dense=1.0, prune_opacity=0.0, prune_screen_radius=1e9,
                               prune_world_scale=1e9, max_gaussians=field.size + 5)
    with caplog.at_level(logging.WARNING):
        strategy.densify_and_prune(field, optimizer, 1, prune_large=False)
        field.gradient_sum[:] = 1.0
        field.gradient_count[:] = 1
        strategy.densify_and_prune(field, optimizer, 2, prune_large=False)
    assert field.size == strategy.max_gaussians
    assert [r.getMessage() for r in caplog.records].count(
        f"model.max_gaussians={strategy.max_gaussians} reached: densification adds no more Gaussians") == 1


def test_nan_in_a_gaussian_parameter_stops_training_naming_it_and_the_step():
    model, optimizer = _fitted_field()
    with torch.no_grad():
        model.gaussians.log_scales[3, 1] = float("nan")
    state = TrainingState(step=7, total_steps=10, optimizer=optimizer)
    with pytest.raises(NonFiniteError, match=r"^step 7: model 'semantic_3dgs' Gaussian parameter 'log_scales' holds "
                                             r"NaN or Inf \(1 of \d+ Gaussians\); training stopped$"):
        model.hooks.check_finite(state)


def test_a_checkpoint_whose_count_differs_from_its_tensors_is_refused():
    model = small_model()
    model.hooks.initialise(model_scene())
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    fresh = small_model()
    load_weights(fresh, weights, "checkpoint x.pt")  # built empty, it takes the checkpoint's size
    assert fresh.gaussians.size == model.gaussians.size
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), model.state_dict().values()))
    weights["gaussians.opacity_logits"] = weights["gaussians.opacity_logits"][:-1]
    with pytest.raises(DataError, match=rf"^checkpoint x.pt: it records {model.gaussians.size} Gaussians "
                                        rf"\(gaussians.count\) but gaussians.opacity_logits has "
                                        rf"{model.gaussians.size - 1} rows"):
        load_weights(small_model(), weights, "checkpoint x.pt")


def test_the_family_passes_the_contract_kit():
    from gpnerf_core.registry.plugins import BUILTIN_PLUGINS
    from gpnerf_core.testing import plugin_checks

    options = {key: value for key, value in SMALL.items() if key != "name"}
    checks = [check for check in plugin_checks(BUILTIN_PLUGINS, configs={"model/semantic_3dgs": options})
              if check.component == "model/semantic_3dgs"]
    assert len(checks) >= 4
    for check in checks:
        check.run()


def test_a_weight_average_or_an_unknown_colour_error_is_refused(tmp_path):
    cfg = compose(["+experiment=baselines/semantic_3dgs", *TINY, "train.ema_decay=0.9"])
    with pytest.raises(ConfigError, match=r"model=semantic_3dgs adds and removes parameters .* expected "
                                          r"train.ema_decay=0 \(got 0.9\)"):
        make_trainer(cfg, tmp_path / "run")
    with pytest.raises(ConfigError, match=r"^loss.rgb_error='l2': expected one of mse, l1$"):
        build_components(compose(["+experiment=baselines/semantic_3dgs", *TINY, "loss.rgb_error=l2"]))


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A 6-step fit (checkpoints at 3 and 6) and its metrics."""
    out = tmp_path_factory.mktemp("semantic_3dgs") / "run"
    argv = ["run", "+experiment=baselines/semantic_3dgs", *TINY, "train.steps=6", "train.checkpoint_every=3",
            f"out_dir={out}"]
    assert cli_main(argv) == 0
    return out


def test_a_run_resumed_after_a_kill_trains_bit_for_bit(fitted, tmp_path):
    straight = json.loads((fitted / "metrics.json").read_text())
    resumed_dir = tmp_path / "resumed"
    middle = fitted / "checkpoints" / "step_0000003.pt"  # what a kill after step 3 leaves
    argv = ["run", "+experiment=baselines/semantic_3dgs", *TINY, "train.steps=6", f"train.resume={middle}",
            f"out_dir={resumed_dir}"]
    assert cli_main(argv) == 0
    resumed = json.loads((resumed_dir / "metrics.json").read_text())
    assert resumed["train"]["final_loss"] == straight["train"]["final_loss"]
    scores = [{k: v for k, v in m["eval"]["train_heldout"].items() if k != "timing"} for m in (straight, resumed)]
    assert scores[0] == scores[1]
    a = torch.load(fitted / "checkpoints" / "step_0000006.pt", weights_only=False)["model"]
    b = torch.load(resumed_dir / "checkpoints" / "step_0000006.pt", weights_only=False)["model"]
    three = torch.load(middle, weights_only=False)["model"]
    assert int(a["gaussians.count"]) != int(three["gaussians.count"])  # it changed size after the checkpoint
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_eval_render_and_export_build_it_at_the_checkpoints_size(fitted, tmp_path):
    checkpoint = fitted / "checkpoints" / "step_0000006.pt"
    count = int(torch.load(checkpoint, weights_only=False)["model"]["gaussians.count"])
    assert cli_main(["eval", f"checkpoint={checkpoint}", f"out_dir={tmp_path / 'eval'}"]) == 0
    scored = json.loads((tmp_path / "eval" / "metrics.json").read_text())["eval"]["train_heldout"]
    trained = json.loads((fitted / "metrics.json").read_text())["eval"]["train_heldout"]
    assert scored["miou/image_mean_present"] == trained["miou/image_mean_present"]
    assert cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"]) == 0
    assert cli_main(["export", f"checkpoint={checkpoint}", f"out_dir={tmp_path / 'export'}"]) == 0
    columns = read_ply((tmp_path / "export" / "gaussians.ply").read_bytes())
    assert len(columns["x"]) == count and len([c for c in columns if c.startswith("f_rest_")]) == 3 * 3
    assert set(np.unique(columns["label"])) <= set(range(21))


def test_a_short_run_of_the_official_schedule_resets_no_opacity_and_says_so_once(tmp_path, capsys):
    out = tmp_path / "short"
    assert cli_main(["run", "+experiment=baselines/semantic_3dgs", *TINY, "model.schedule_steps=30000",
                     "model.opacity_reset_every=3000", "train.steps=2", "eval.max_views_per_scene=1",
                     f"out_dir={out}"]) == 0
    err = capsys.readouterr().err
    assert err.count("note: model.opacity_reset_every=3000 of a 30000-step schedule (model.schedule_steps) scaled to "
                     "2 steps would cap every opacity at 0.01 every 1 step(s), under 50") == 1
    assert "this run resets no opacity" in err


def test_it_trains_in_bf16_the_rasterizer_working_in_float32(tmp_path):
    out = tmp_path / "bf16"
    assert cli_main(["run", "+experiment=baselines/semantic_3dgs", *TINY, "train.steps=2", "train.precision=bf16",
                     "eval.max_views_per_scene=1", f"out_dir={out}"]) == 0
    assert json.loads((out / "metrics.json").read_text())["train"]["precision"] == "bf16"


def test_export_writes_the_gaussians_when_the_fusion_keeps_no_point(fitted, tmp_path, capsys):
    checkpoint = fitted / "checkpoints" / "step_0000006.pt"
    count = int(torch.load(checkpoint, weights_only=False)["model"]["gaussians.count"])
    out = tmp_path / "export"
    assert cli_main(["export", f"checkpoint={checkpoint}", "export.tolerance=1e-9", f"out_dir={out}"]) == 0
    assert "no point of scene 'layout_00' is inside its depth bounds" in capsys.readouterr().err
    written = sorted(p.name for p in out.iterdir() if p.suffix in (".ply", ".json") and p.name != "plugins.json")
    assert written == ["export.json", "gaussians.ply"]
    assert len(read_ply((out / "gaussians.ply").read_bytes())["x"]) == count
    assert "the point cloud is not written" in json.loads((out / "export.json").read_text())["note"]


def test_stress_skips_what_a_per_scene_model_cannot_be_asked(fitted, tmp_path):
    out = tmp_path / "stress"
    assert cli_main(["stress", str(fitted), "--quick", "--threads", "1", "--cases", "unseen,textureless,source_views",
                     "--out", str(out)]) == 0
    outcomes = json.loads((out / "stress.json").read_text())["outcomes"]
    assert outcomes[0]["case"] == "clean" and outcomes[0]["method"] == "Semantic 3DGS (image)"
    reasons = {o["case"]: o["skipped"] for o in outcomes[1:]}
    assert "is fitted on its own scene's frames (per-scene): another scene" in reasons["unseen"]
    assert reasons["textureless"] == reasons["unseen"] and "no source views to change" in reasons["source_views"]


def test_the_viewer_draws_the_fitted_gaussians_themselves(fitted):
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.engine.opening import open_trained
    from gpnerf_core.model.feature_cache import SourceFeatureCache
    from gpnerf_core.model.trained import load_trained
    from gpnerf_core.tools.viewer.renderer import SceneRenderer
    from gpnerf_core.tools.viewer.splats import splat_arrays

    trained = load_trained(fitted / "checkpoints" / "step_0000006.pt")
    components = open_trained(trained, command="view", weights="trained", device=torch.device("cpu")).components
    renderer = SceneRenderer(components.model.eval(), FrameCache(components.dataset, torch.device("cpu")),
                             components.view_selector, num_classes=components.classes.num_classes, chunk_rays=256,
                             default_source_views=0, feature_cache=SourceFeatureCache(16))
    splats = renderer.gaussians("layout_00", ())  # a per-scene model: no source views, its own Gaussians
    assert renderer.draws_gaussians and splats.count == int(trained.state["model"]["gaussians.count"])
    assert splat_arrays(splats, "class", renderer.num_classes)["centers"].shape == (splats.count, 3)


def _kit_failures(hooks_methods: dict, **capabilities) -> dict[str, str]:
    """``{check: message}`` of the contract kit's failed checks of semantic_3dgs with its hooks' ``hooks_methods``
    replaced (and ``capabilities`` changed), registered as ``broken_3dgs``."""
    import types

    from gpnerf_core import ComponentSpec, hookimpl
    from gpnerf_core.testing import check_plugin
    from gpnerf_plugins.families.semantic_3dgs.build import build_semantic_3dgs
    from gpnerf_plugins.families.semantic_3dgs.config import Semantic3DGSConfig
    from gpnerf_plugins.families.semantic_3dgs.model import Semantic3DGS

    hooks = type("BrokenHooks", (Semantic3DGS.capabilities.hooks,), hooks_methods)
    family = type("Broken3DGS", (Semantic3DGS,), {"capabilities": dataclasses.replace(
        Semantic3DGS.capabilities, hooks=hooks, **capabilities)})
    config = dataclasses.make_dataclass("BrokenConfig", [("name", str, dataclasses.field(default="broken_3dgs"))],
                                        bases=(Semantic3DGSConfig,))

    def build(**options) -> family:
        built = build_semantic_3dgs(**options)
        broken = family.__new__(family)
        broken.__dict__ = built.__dict__
        return broken

    module = types.ModuleType("broken_3dgs_plugin")
    module.gpnerf_register_models = hookimpl(lambda: [ComponentSpec("broken_3dgs", build, config)])
    options = {key: value for key, value in SMALL.items() if key not in ("name", "schedule_steps")}
    results = check_plugin(module, configs={"model/broken_3dgs": options}, raise_on_failure=False)
    return {result.check: result.message for result in results if result.failed}


def test_the_contract_kit_densifies_and_fails_what_a_densification_gets_wrong():
    def skips_optimizer(self, state):
        gaussians = self.family.gaussians
        gaussians.set_rows({name: torch.cat([row.detach(), row.detach()[:1]]) for name, row in gaussians.rows().items()})

    def never(self, state):
        pass

    def turns_nan(self, state):
        type(self).__mro__[1].density_control(self, state)
        if state.step == 3:
            with torch.no_grad():
                self.family.gaussians.means[0, 0] = float("nan")

    def keeps_size(self, weights, source):
        pass

    no_finite_check = {"callbacks": lambda self: tuple(c for c in type(self).__mro__[1].callbacks(self)
                                                       if c.run != self.check_finite)}
    assert "replaced without the optimizer" in _kit_failures({"density_control": skips_optimizer})["training hooks"]
    assert "no parameter changed size in 6 steps" in _kit_failures({"density_control": never})["training hooks"]
    assert ("after step 3: parameter 'gaussians.means' holds NaN or Inf"
            in _kit_failures({"density_control": turns_nan, **no_finite_check})["training hooks"])
    assert "loading its saved weights into a fresh build" in _kit_failures({"resize_to": keeps_size})["training hooks"]
