"""The ``nearest`` view selector: ranking, determinism, pool randomness, edge cases."""

from __future__ import annotations

import math

import pytest
import torch

from gpnerf_core.errors import ConfigError, DataError, NonFiniteError
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_plugins.view_selectors.nearest import NearestViews, NearestViewsConfig


def _look_at(eye: tuple[float, float, float], target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    eye_t = torch.tensor(eye, dtype=torch.float64)
    forward = torch.nn.functional.normalize(torch.tensor(target, dtype=torch.float64) - eye_t, dim=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    down = torch.linalg.cross(forward, right)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye_t
    return c2w.float()


def _orbit(n: int, radius: float = 2.0) -> torch.Tensor:
    """n cameras on a circle looking at the origin; camera k at angle 2 pi k / n."""
    return torch.stack([
        _look_at((radius * math.cos(2 * math.pi * k / n), radius * math.sin(2 * math.pi * k / n), 1.0)) for k in range(n)
    ])


def test_deterministic_choice_is_the_nearest_on_an_orbit():
    cams = _orbit(24)
    selector = NearestViews()
    picked = selector.select(cams[0], cams[1:], 4)  # candidate position p is camera p + 1
    assert picked == selector.select(cams[0], cams[1:], 4)
    assert sorted(p + 1 for p in picked) == [1, 2, 22, 23]
    assert {picked[0] + 1, picked[1] + 1} == {1, 23}  # ordered best first


def test_angle_term_breaks_a_distance_tie():
    target = _look_at((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    same_direction = _look_at((1.0, 0.0, 0.0), (1.0, 1.0, 0.0))
    turned_away = _look_at((-1.0, 0.0, 0.0), (-2.0, 0.0, 0.0))
    candidates = torch.stack([turned_away, same_direction])
    assert NearestViews(angle_weight=0.5).select(target, candidates, 1) == [1]
    scores = NearestViews(angle_weight=0.0).scores(target, candidates)
    assert torch.allclose(scores[0], scores[1])


def test_generator_draws_from_the_pool_reproducibly_and_without_duplicates():
    cams = _orbit(36)
    selector = NearestViews(pool_factor=2)
    best = selector.select(cams[0], cams[1:], 10)
    pool = set(torch.sort(selector.scores(cams[0], cams[1:]), stable=True).indices[:20].tolist())
    draws = set()
    for seed in range(20):
        picked = selector.select(cams[0], cams[1:], 5, generator=torch.Generator().manual_seed(seed))
        assert len(picked) == len(set(picked)) == 5
        assert set(picked) <= set(selector.select(cams[0], cams[1:], 10)) <= pool
        again = selector.select(cams[0], cams[1:], 5, generator=torch.Generator().manual_seed(seed))
        assert picked == again
        draws.add(tuple(sorted(picked)))
    assert len(draws) > 5, "a generator must randomize the choice within the pool"
    assert set(best) <= pool


def test_pool_factor_one_with_generator_equals_the_deterministic_choice():
    cams = _orbit(12)
    selector = NearestViews(pool_factor=1)
    expected = selector.select(cams[3], cams, 4)
    got = selector.select(cams[3], cams, 4, generator=torch.Generator().manual_seed(7))
    assert sorted(got) == sorted(expected)


@pytest.mark.parametrize("generator_seed", [None, 3])
def test_fewer_candidates_than_requested(generator_seed):
    cams = _orbit(8)
    gen = None if generator_seed is None else torch.Generator().manual_seed(generator_seed)
    picked = NearestViews().select(cams[0], cams[1:4], 10, generator=gen)
    assert sorted(picked) == [0, 1, 2]
    assert NearestViews().select(cams[0], cams[:0], 3) == []


def test_bad_arguments_raise_one_line_errors():
    cams = _orbit(6)
    with pytest.raises(ConfigError, match="num_views"):
        NearestViews().select(cams[0], cams, 0)
    with pytest.raises(ConfigError, match="pool_factor"):
        NearestViews(pool_factor=0)
    with pytest.raises(ConfigError, match="angle_weight"):
        NearestViews(angle_weight=-1.0)
    with pytest.raises(DataError, match="expected \\(N, 4, 4\\)"):
        NearestViews().select(cams[0], cams[:, :3], 2)
    broken = cams.clone()
    broken[2, 0, 3] = float("nan")
    with pytest.raises(NonFiniteError):
        NearestViews().select(cams[0], broken, 2)


def test_registered_and_built_from_config():
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.view_selectors.plugin",), autoload=False))
    assert not registry.problems
    selector = registry.build("view_selector", {"name": "nearest", "pool_factor": 3, "angle_weight": 1.0})
    assert isinstance(selector, NearestViews)
    assert (selector.pool_factor, selector.angle_weight) == (3, 1.0)
    assert NearestViewsConfig().name == "nearest"
