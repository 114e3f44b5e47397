"""A cheap depth per ray from the source views (``model.depth_source=cost_volume|source_depth``): the plane sweep of
their features and their recorded depth find a textured wall at its depth, tell nothing where the views do not see or
record it (flat beliefs, samples along the whole ray), and the GNT family renders one pass on samples around it."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry import pixel_grid, rays_through_pixels, surface_depths
from gpnerf_core.geometry.ray_depth import feature_cost_belief, source_depth_belief
from gpnerf_core.model.build import build_components
from gpnerf_core.types import SourceViews
from pipeline_check import KIT_PARTS, TINY_MODEL, TINY_SCENES

HEIGHT, WIDTH, FOCAL, WALL = 48, 64, 50.0, 2.0
K = torch.tensor([[FOCAL, 0.0, WIDTH / 2 - 0.5], [0.0, FOCAL, HEIGHT / 2 - 0.5], [0.0, 0.0, 1.0]])


def _camera(x: float) -> torch.Tensor:
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return c2w


def _wall_views(offsets=(-0.3, 0.0, 0.3), depth_known: bool = True) -> SourceViews:
    """Cameras at x = ``offsets`` looking along +z at a textured wall z = WALL (their images and depth, exactly)."""
    v, u = torch.meshgrid(torch.arange(HEIGHT, dtype=torch.float32), torch.arange(WIDTH, dtype=torch.float32),
                          indexing="ij")
    images = []
    for x in offsets:
        wall_x, wall_y = x + (u - K[0, 2]) / FOCAL * WALL, (v - K[1, 2]) / FOCAL * WALL
        images.append(torch.stack([torch.sin(7 * wall_x) * 0.5 + 0.5, torch.cos(5 * wall_y + 3 * wall_x) * 0.5 + 0.5,
                                   torch.sin(11 * wall_x * wall_y + 1) * 0.5 + 0.5]))
    views = len(offsets)
    depth = torch.full((views, HEIGHT, WIDTH), WALL if depth_known else 0.0)
    return SourceViews(rgb=torch.stack(images), intrinsics=K.expand(views, 3, 3),
                       c2w=torch.stack([_camera(x) for x in offsets]), depth=depth)


def _target_rays():
    return rays_through_pixels(pixel_grid(HEIGHT, WIDTH, 4), K, _camera(0.15), 0.5, 6.0)


def test_the_recorded_depth_of_the_sources_puts_every_ray_on_the_wall():
    rays, sources = _target_rays(), _wall_views()
    belief = source_depth_belief(rays, sources, planes=64)
    assert belief.evidence.all()
    assert torch.allclose(belief.probabilities.sum(-1), torch.ones(rays.num_rays))
    assert (belief.expected_depth - WALL).abs().max() < 0.05
    samples, certain = surface_depths(rays, belief.depths, belief.probabilities, 8, spread=2.0, uncertainty=0.2,
                                      perturb=False)
    assert certain.all() and (samples - WALL).abs().max() < 0.3  # 8 samples within a few bins of the wall


def test_the_feature_sweep_finds_the_textured_wall_on_most_rays():
    rays, sources = _target_rays(), _wall_views()
    belief = feature_cost_belief(rays, sources, sources.rgb, planes=64)
    error = (belief.depths.gather(1, belief.probabilities.argmax(-1, keepdim=True))[:, 0] - WALL).abs()
    assert belief.evidence.all() and error.median() < 0.1
    _, certain = surface_depths(rays, belief.depths, belief.probabilities, 8, spread=2.0, uncertainty=0.2,
                                perturb=False)
    assert certain.float().mean() > 0.4  # a per-pixel colour sweep is ambiguous on part of the wall


def test_rays_the_sources_tell_nothing_about_get_samples_along_the_whole_ray():
    rays = _target_rays()
    unknown = source_depth_belief(rays, _wall_views(depth_known=False), planes=32)
    assert not unknown.evidence.any()
    assert torch.allclose(unknown.probabilities, torch.full_like(unknown.probabilities, 1 / 32))
    samples, certain = surface_depths(rays, unknown.depths, unknown.probabilities, 8, spread=2.0, uncertainty=0.2,
                                      perturb=False)
    assert not certain.any() and (samples[:, 0] < 0.7).all() and (samples[:, -1] > 5.0).all()
    behind = _wall_views()
    behind = SourceViews(rgb=behind.rgb, intrinsics=behind.intrinsics, c2w=behind.c2w.clone(), depth=behind.depth)
    behind.c2w[:, 2, 3] = 10.0  # every source camera behind the rays' far end, looking away: no candidate is seen
    unseen = feature_cost_belief(rays, behind, behind.rgb, planes=16)
    assert not unseen.evidence.any() and torch.isfinite(unseen.probabilities).all()
    with pytest.raises(ValueError, match="needs the source views' depth"):
        source_depth_belief(rays, SourceViews(rgb=behind.rgb, intrinsics=behind.intrinsics, c2w=behind.c2w), planes=8)


@pytest.mark.parametrize("source", ["cost_volume", "source_depth"])
def test_the_gnt_family_renders_one_pass_on_samples_around_the_swept_depth(tmp_path, source):
    common = ["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"]
    model = build_components(compose([*common, "model.sampler=depth", f"+depth_source={source}",
                                      "depth_source.planes=32", "model.fine_samples=4"])).model
    rays, sources = _target_rays(), _wall_views()
    with torch.no_grad():
        only, none = model.render_rays(rays, sources, model.encode(sources.rgb), randomized=False, with_semantic=True)
    assert none is None and only.samples.depths.shape == (rays.num_rays, 4)
    assert only.semantic is not None and torch.isfinite(only.rgb).all()
    if source == "source_depth":  # around the wall, within about one of the 32 candidate bins (0.24 m there)
        depths = only.samples.depths
        assert (depths[:, 0] < WALL).all() and (depths[:, -1] > WALL).all() and (depths - WALL).abs().max() < 0.5
    with pytest.raises(ConfigError, match=rf"^depth_source={source} places the samples of model.sampler=depth; "
                                          r"expected model.sampler=depth with it \(model.sampler is 'uniform'\)$"):
        build_components(compose([*common, f"+depth_source={source}"]))
    with pytest.raises(ConfigError, match=r"^depth_source.planes=1: expected an integer >= 2"):
        build_components(compose([*common, "model.sampler=depth", f"+depth_source={source}", "depth_source.planes=1"]))


def test_a_depth_source_or_head_the_model_does_not_use_is_refused_not_ignored():
    from gpnerf_core.model.build import build_model

    with pytest.raises(ConfigError, match=r"^\+depth_source=cost_volume: model 'semantic_nerf' as configured uses no "
                                          r"depth_source \(it would be ignored\)"):
        build_model(compose(["+experiment=baselines/semantic_nerf", "+depth_source=cost_volume"]), num_classes=4)


@pytest.mark.parametrize("family", ["neuray", "semantic_ray", "mvsnerf"])
def test_the_compared_families_render_one_pass_around_a_depth_source(family):
    """``model.sampler=depth +depth_source=<name>`` is a sampler any family can take: the compared families render one
    pass on ``fine_samples`` samples around the source's depth, in training (jittered) and in a whole view."""
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.testing.inputs import kit_parts, model_batch, model_view

    registry = get_registry()
    parts = kit_parts(registry, family, head=False, parts=KIT_PARTS)
    parts._cfg.depth_source = {"name": "cost_volume", "planes": 16}
    node = {"name": family, "coarse_samples": 6, "fine_samples": 3, "sampler": "depth"}
    model = registry.build("model", node, parts=parts)
    view = model(model_batch(sources=True), semantics=True).views[0]
    assert view.fine is None and view.coarse.samples.depths.shape[-1] == 3
    assert torch.isfinite(view.coarse.rgb).all() and torch.isfinite(view.coarse.logits).all()
    camera, sources = model_view(sources=True)
    prediction = model.eval().predict(camera, sources, stride=4, chunk_rays=50)
    assert torch.isfinite(prediction.rgb).all() and torch.isfinite(prediction.logits).all()
    with pytest.raises(ConfigError, match=rf"^model={family} model.sampler=depth renders one pass on "
                                          r"model.fine_samples samples around a \+depth_source's depth"):
        registry.build("model", node, parts=kit_parts(registry, family, head=False, parts=KIT_PARTS))


@pytest.mark.parametrize("family", ["neuray", "semantic_ray", "mvsnerf"])
def test_the_compared_families_preview_a_few_samples_around_a_depth_source_and_restore_their_sampling(family):
    """The viewer's preview (``ModelFamily.preview_sampling``) of a family trained with its own two passes: one pass
    of its last network on the preview's samples around the depth source's depth, with the decoded semantics; the
    configured sampling is back afterwards, also after a failure."""
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.testing.inputs import kit_parts, model_view
    from gpnerf_plugins.depth_sources.sweeps import CostVolumeDepth

    registry = get_registry()
    model = registry.build("model", {"name": family, "coarse_samples": 6, "fine_samples": 4},
                           parts=kit_parts(registry, family, head=True, parts=KIT_PARTS)).eval()
    camera, sources = model_view(sources=True)
    configured = (model.sampling, model.depth_source, model.fine_samples)
    full = model.predict(camera, sources, stride=4, chunk_rays=50)
    sweep = CostVolumeDepth(planes=16)
    asked = []
    sample_depths = sweep.sample_depths
    sweep.sample_depths = lambda *args, **kwargs: asked.append(args[3]) or sample_depths(*args, **kwargs)
    with model.preview_sampling(sweep, 2) as honoured:
        preview = model.predict(camera, sources, stride=4, chunk_rays=50)
    assert honoured and asked and set(asked) == {2}
    assert (model.sampling, model.depth_source, model.fine_samples) == configured
    assert preview.logits.shape == full.logits.shape and torch.isfinite(preview.logits).all()
    assert torch.isfinite(preview.rgb).all() and not torch.equal(preview.rgb, full.rgb)
    with pytest.raises(RuntimeError, match="render failed"), model.preview_sampling(sweep, 2):
        raise RuntimeError("render failed")
    assert (model.sampling, model.depth_source, model.fine_samples) == configured
    with pytest.raises(ConfigError, match=r"^a preview needs at least 1 sample per ray, got 0"):
        with model.preview_sampling(sweep, 0):
            pass
