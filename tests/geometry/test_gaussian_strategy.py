"""The public Gaussian strategy (``gpnerf_core.geometry.gaussians``): parameters whose rows change with their optimizer
state and statistics, starts from points or from another model's Gaussians, and density control as strategies
(3DGS's official schedule scaled to a run, a budget the count never exceeds)."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core import (
    BudgetedStrategy,
    ConfigError,
    DefaultStrategy,
    GaussianParameters,
    GaussianScene,
    ViewInfo,
    append_rows,
    keep_rows,
    rows_from_gaussians,
    rows_from_points,
)


def fitted(count: int = 40, channels: int = 2, strategy: DefaultStrategy | None = None):
    """Parameters of ``count`` small Gaussians, an Adam over each row and one step taken (moments not zero)."""
    torch.manual_seed(0)
    params = GaussianParameters(1, {"features": channels})
    (strategy or DefaultStrategy()).initialize_state(params)
    xyz = torch.rand(count, 3)
    rows = rows_from_points(xyz, torch.rand(count, 3), torch.full((count,), 0.001), sh_degree=1, opacity=0.5)
    rows["features"] = torch.randn(count, channels)
    params.set_rows(rows)
    optimizer = torch.optim.Adam([{"params": [p], "lr": 0.01, "name": n} for n, p in params.rows().items()])
    for p in params.parameters():
        p.grad = torch.ones_like(p)
    optimizer.step()
    return params, optimizer


def test_rows_added_and_kept_carry_their_moments_and_statistics():
    params, optimizer = fitted()
    params.gradient_sum[:] = torch.arange(40.0)
    moments = optimizer.state[params.features]["exp_avg"].clone()
    append_rows(params, optimizer, {name: tensor[:3] for name, tensor in params.rows().items()})
    assert params.size == 43 and int(params.count) == 43
    assert torch.equal(params.gradient_sum[40:], torch.zeros(3)) and torch.equal(params.gradient_sum[:40],
                                                                                 torch.arange(40.0))
    keep = torch.ones(43, dtype=torch.bool)
    keep[5] = False
    keep_rows(params, optimizer, keep)
    state = optimizer.state[params.features]["exp_avg"]
    assert params.size == 42 and torch.equal(state[:5], moments[:5]) and torch.equal(state[5:39], moments[6:])
    assert torch.equal(state[39:], torch.zeros(3, 2)) and params.gradient_sum[5] == 6.0
    DefaultStrategy().check_sanity(params, optimizer)  # every row is in the optimizer, one group each


def test_a_row_the_optimizer_does_not_step_is_refused_naming_it():
    params, _ = fitted()
    optimizer = torch.optim.Adam([{"params": [p], "name": n} for n, p in params.rows().items() if n != "features"])
    with pytest.raises(ConfigError, match=r"Gaussian parameter 'features' is not in the optimizer"):
        DefaultStrategy().check_sanity(params, optimizer)


def test_another_models_gaussians_start_the_rows_and_come_back_the_same():
    torch.manual_seed(1)
    count = 25
    harmonics = torch.randn(count, 3, 9)  # degree 2 from the other model
    scene = GaussianScene(means=torch.randn(count, 3), scales=torch.rand(count, 3) * 0.1 + 0.01,
                          rotations=torch.nn.functional.normalize(torch.randn(count, 4), dim=-1),
                          opacities=torch.rand(count) * 0.9 + 0.05, harmonics=harmonics,
                          labels=torch.arange(count))
    params = GaussianParameters(3, {})
    params.set_rows(rows_from_gaussians(scene, sh_degree=3))  # padded with zeros to degree 3
    back = params.as_scene(scene.labels)
    for name in ("means", "scales", "rotations", "opacities"):
        assert torch.allclose(getattr(back, name), getattr(scene, name), atol=1e-6), name
    assert torch.equal(back.harmonics[..., :9], harmonics) and not back.harmonics[..., 9:].any()
    params = GaussianParameters(0, {})
    params.set_rows(rows_from_gaussians(scene, sh_degree=0))  # cut to degree 0
    assert params.harmonics_rest.shape == (count, 3, 0) and torch.equal(params.harmonics_dc, harmonics[..., 0])


def test_the_official_schedule_scales_to_a_runs_length():
    strategy = DefaultStrategy().scaled(3000)  # a tenth of 3DGS's 30k iterations
    assert (strategy.densify_from, strategy.densify_until, strategy.densify_every, strategy.opacity_reset_every) == (
        50, 1500, 10, 300)
    assert DefaultStrategy().scaled(20).densify_every == 1  # never below one step


def test_opacity_resets_scaled_closer_than_the_floor_are_dropped_for_the_run_and_said():
    """A 20-step run of the official schedule would cap every opacity at 0.01 at every step of its first half (the
    render turns near-black): it resets none and says why; 600- and 2000-step runs keep the official scaling exactly
    (bit for bit), 495 is the shortest run of the official schedule that keeps the resets."""
    official = DefaultStrategy()
    for steps, interval in ((600, 60), (2000, 200), (495, 50), (3000, 300)):
        scaled = official.scaled(steps)
        assert scaled.opacity_reset_every == interval and not official.resets_dropped(steps)
        assert official.schedule_note(steps) is None
        assert (scaled.densify_from, scaled.densify_until, scaled.densify_every) == tuple(
            max(1, round(v * steps / 30000)) for v in (500, 15000, 100))
    for steps in (20, 40, 494):
        assert official.resets_dropped(steps) and official.scaled(steps).opacity_reset_every == steps + 1
    note = official.schedule_note(20)
    assert note.startswith("model.opacity_reset_every=3000 of a 30000-step schedule (model.schedule_steps) scaled to "
                           "20 steps would cap every opacity at 0.01 every 2 step(s), under 50:")
    assert "this run resets no opacity" in note and note.endswith("runs of 495 steps or more keep the resets")
    # an interval configured short on purpose (the schedule run as written) is kept
    explicit = DefaultStrategy(opacity_reset_every=4, schedule_steps=6)
    assert explicit.scaled(6).opacity_reset_every == 4 and explicit.schedule_note(6) is None
    # the 20-step run's density control never touches an opacity
    params, optimizer = fitted(strategy=official)
    before = params.opacity_logits.detach().clone()
    run = official.scaled(20)
    for step in range(20):
        run.step_post_backward(params, optimizer, params.row_state(), step, [])
    assert torch.equal(params.opacity_logits.detach(), before)
    assert BudgetedStrategy().scaled(20).opacity_reset_every == 21


def _view(params: GaussianParameters, gradient: torch.Tensor) -> ViewInfo:
    means2d = torch.zeros(params.size, 2, requires_grad=True)
    means2d.grad = torch.stack([gradient, torch.zeros_like(gradient)], dim=-1)
    return ViewInfo(means2d=means2d, radii=torch.ones(params.size, dtype=torch.int32), height=2, width=2)


def test_a_budget_is_never_exceeded_and_the_largest_gradients_grow_first():
    budget = 60
    strategy = BudgetedStrategy(grad_threshold=0.5, percent_dense=1.0, prune_opacity=0.0, prune_screen_radius=1e9,
                                prune_world_scale=1e9, densify_from=1, densify_until=11, densify_every=1,
                                opacity_reset_every=1000, budget=budget, schedule_steps=20)
    params, optimizer = fitted(strategy=strategy)
    sizes = []
    for step in range(12):
        gradient = torch.linspace(1.0, 2.0, params.size)  # every Gaussian a candidate, the last rows the largest
        marked = params.means[:, 0].detach().clone()
        strategy.step_post_backward(params, optimizer, params.row_state(), step, [_view(params, gradient)])
        sizes.append(params.size)
        if step == 1:  # the first densification: the budget allows 40 + 20 / 10 = 42, the two largest grow
            assert params.size == 42 and torch.equal(params.means[40:, 0], marked[38:40])
    assert max(sizes) <= budget and sizes == sorted(sizes) and sizes[-1] == 40 + 20 * 9 // 10  # the last at 90 %
    with pytest.raises(ConfigError, match=r"the Gaussians start with 61 rows, above the budget of 60"):
        strategy.check_start(61)


def _scene(count: int = 5, **replaced) -> GaussianScene:
    fields = dict(means=torch.zeros(count, 3), scales=torch.ones(count, 3), rotations=torch.ones(count, 4),
                  opacities=torch.full((count,), 0.5), harmonics=torch.zeros(count, 3, 4),
                  labels=torch.zeros(count, dtype=torch.long))
    return GaussianScene(**{**fields, **replaced})


@pytest.mark.parametrize("replaced, expected", [
    ({"labels": torch.zeros(4, dtype=torch.long)}, "its labels has 4 rows for 5 means"),
    ({"opacities": torch.zeros(5, 1)}, "its opacities is [5, 1], expected [5]"),
    ({"harmonics": torch.zeros(5, 3, 3)}, "its harmonics is [5, 3, 3], expected [5, 3, (degree + 1)^2]"),
    ({"labels": torch.zeros(5)}, "its labels are torch.float32, expected integers"),
    ({"labels": torch.full((5,), 7)}, "its labels reach 7; expected -1 (none) or an output of semantic_output (0 to 2)"),
])
def test_scene_problem_names_the_column_export_would_fail_on(replaced, expected):
    from gpnerf_core.geometry.gaussians.scene import scene_problem

    assert scene_problem(_scene(), 3) is None
    assert expected in scene_problem(_scene(**replaced), 3)
    assert "expected a gpnerf_core.GaussianScene" in scene_problem(object(), 3)


def test_export_refuses_columns_of_another_length_in_one_line_naming_the_plugin():
    from types import SimpleNamespace

    from gpnerf_core.commands.export import scene_gaussians
    from gpnerf_core.errors import PluginError
    from gpnerf_core.interfaces.model import Capabilities

    model = SimpleNamespace(capabilities=Capabilities(gaussians=True), semantic_output=None,
                            scene_gaussians=lambda sources, **_: _scene(labels=torch.zeros(4, dtype=torch.long)))
    given = SimpleNamespace(sources=None, features=None)
    with pytest.raises(PluginError) as error:
        scene_gaussians(model, given, SimpleNamespace(near=0.1, far=5.0), {"colour": "model 'semantic_3dgs'"}, "s")
    message = str(error.value)
    assert "\n" not in message and "its labels has 4 rows for 5 means" in message and "nothing was written" in message
    assert "plugin gpnerf_plugins" in message  # the registry's record of the family names its plugin
