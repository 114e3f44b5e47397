"""Samples where the surfaces are (``model.sampler=depth``): around a first pass's depth where it is certain, drawn from
its weights where it is not; and the GNT family's fine pass built on them."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry import importance_depths, stratified_inverse_depths, surface_depths
from gpnerf_core.model.build import build_components
from gpnerf_core.types import RayBatch
from pipeline_check import TINY_MODEL, TINY_SCENES


def _rays(count: int, near: float = 0.5, far: float = 8.0) -> RayBatch:
    return RayBatch(origins=torch.zeros(count, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]).expand(count, 3),
                    pixels=torch.zeros(count, 2), near=torch.full((count,), near), far=torch.full((count,), far))


def test_a_peaked_ray_gets_its_samples_around_its_depth_and_a_flat_one_along_the_whole_ray():
    rays = _rays(2)
    depths = stratified_inverse_depths(rays, 24, perturb=False)
    weights = torch.full_like(depths, 1e-4)
    surface = int((depths[0] - 2.0).abs().argmin())
    weights[0, surface] = 1.0  # ray 0 meets a surface at about 2 m
    weights[1] = 1.0 / depths.shape[-1]  # ray 1: nothing stands out
    chosen, certain = surface_depths(rays, depths, weights, 8, spread=2.0, uncertainty=0.2, perturb=False)
    assert chosen.shape == (2, 8) and certain.tolist() == [True, False]
    bin_width = depths[0, surface] ** 2 * (1 / 0.5 - 1 / 8.0) / 23
    assert (chosen[0] - depths[0, surface]).abs().max() <= bin_width * 1.01 + 1e-4
    # the uncertain ray: importance samples of its flat weights, spread along the whole ray
    assert torch.equal(chosen[1], importance_depths(depths, weights, 8, deterministic=True)[1])
    assert chosen[1, 0] < 0.7 and chosen[1, -1] > 6.0
    assert torch.all(chosen[:, 1:] >= chosen[:, :-1])


def test_the_span_grows_with_the_spread_and_stays_inside_the_ray():
    rays = _rays(1)
    depths = stratified_inverse_depths(rays, 64, perturb=False)
    weights = torch.exp(-0.5 * ((depths - 3.0) / 0.3) ** 2)  # a peak 0.3 m wide at 3 m (coarse bins there: 0.27 m)
    narrow, _ = surface_depths(rays, depths, weights, 6, spread=1.0, uncertainty=0.5, perturb=False)
    wide, certain = surface_depths(rays, depths, weights, 6, spread=3.0, uncertainty=0.5, perturb=False)
    assert certain.item()
    assert (wide[0, -1] - wide[0, 0]) > 2.5 * (narrow[0, -1] - narrow[0, 0])
    at_far = torch.exp(-0.5 * ((depths - 7.9) / 0.3) ** 2)
    clipped, _ = surface_depths(rays, depths, at_far, 6, spread=3.0, uncertainty=0.5, perturb=False)
    assert clipped.max() == 8.0 and clipped.min() >= 0.5


def test_training_jitter_stays_in_the_span_and_follows_the_generator():
    rays = _rays(4)
    depths = stratified_inverse_depths(rays, 16, perturb=False)
    weights = torch.softmax(-((depths - 3.0) ** 2) * 20, dim=-1)
    exact, _ = surface_depths(rays, depths, weights, 5, spread=2.0, uncertainty=0.2, perturb=False)
    draws = [surface_depths(rays, depths, weights, 5, spread=2.0, uncertainty=0.2, perturb=True,
                            generator=torch.Generator().manual_seed(3))[0] for _ in range(2)]
    assert torch.equal(draws[0], draws[1]) and not torch.equal(draws[0], exact)
    assert draws[0].min() >= exact.min() - 1e-6 and draws[0].max() <= exact.max() + 1e-6


def test_the_gnt_fine_pass_with_sampler_depth_renders_only_its_surface_samples(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                   "model.sampler=depth", "model.coarse_samples=6", "model.fine_samples=3"])
    model = build_components(cfg).model
    rays = _rays(5, near=0.2, far=6.5)
    views = 2
    sources_c2w = torch.eye(4).repeat(views, 1, 1)
    sources_c2w[1, 0, 3] = 0.2
    from gpnerf_core.types import SourceViews

    sources = SourceViews(rgb=torch.rand(views, 3, 32, 48), intrinsics=torch.tensor(
        [[30.0, 0, 23.5], [0, 30.0, 15.5], [0, 0, 1]]).repeat(views, 1, 1), c2w=sources_c2w)
    with torch.no_grad():
        features = model.encode(sources.rgb)
        coarse, fine = model.render_rays(rays, sources, features, randomized=False, with_semantic=True)
    assert coarse.samples.depths.shape == (5, 6) and fine.samples.depths.shape == (5, 3)
    assert fine.semantic is not None and torch.isfinite(fine.depth).all()
    with pytest.raises(ConfigError, match=r"^model.sampler='everywhere'; expected one of: uniform, depth$"):
        build_components(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES,
                                  f"dataset.root={tmp_path / 'scenes'}", "model.sampler=everywhere"]))
    with pytest.raises(ConfigError, match=r"model.sampler=depth .* expected model.fine_samples >= 1"):
        build_components(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES,
                                  f"dataset.root={tmp_path / 'scenes'}", "model.sampler=depth", "model.fine_samples=0"]))
