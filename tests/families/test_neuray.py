"""NeuRay + semantic head and Semantic-Ray (``model=neuray``, ``model=semantic_ray``): the parts that carry the method
(visibility from reprojected depth, the mixture of logistics, query-masked attention, source-ray intervals) and the
contract a family with no head keeps."""

import dataclasses
import math
import types

import pytest
import torch

import model_family
from gpnerf_core import ComponentSpec, SourceViews, hookimpl
from gpnerf_core.testing import check_plugin
from gpnerf_core.types import RayBatch
from gpnerf_plugins.families.neuray.aggregator import QueryMaskedAttention, sinusoidal_code
from gpnerf_plugins.families.neuray.model import VisibilityAwareRenderer
from gpnerf_plugins.families.neuray.visibility import (
    VisibilityDecoder,
    consistency_features,
    normalized_inverse_depth,
)
from pipeline_check import KIT_PARTS

HEIGHT, WIDTH, NEAR, FAR = 24, 32, 0.5, 6.0
K = torch.tensor([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])


def camera_at(x: float) -> torch.Tensor:
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return c2w


def wall(depth_of_view_1: float = 2.0) -> SourceViews:
    """Two cameras 0.2 m apart looking down +z at a wall 2 m away; view 1's depth map says ``depth_of_view_1``."""
    depth = torch.stack([torch.full((HEIGHT, WIDTH), 2.0), torch.full((HEIGHT, WIDTH), depth_of_view_1)])
    return SourceViews(rgb=torch.full((2, 3, HEIGHT, WIDTH), 0.5), intrinsics=K.expand(2, 3, 3).clone(),
                       c2w=torch.stack([camera_at(0.0), camera_at(0.2)]), depth=depth)


def test_consistent_depth_reprojects_without_error_and_wrong_depth_is_seen():
    consistent = consistency_features(wall(), NEAR, FAR)  # [V, 8, H, W]
    assert consistent.shape == (2, 8, HEIGHT, WIDTH)
    assert consistent[0, 3].abs().max() < 1e-4 and consistent[:, :3].abs().max() < 1e-6
    wrong = consistency_features(wall(depth_of_view_1=3.0), NEAR, FAR)
    expected = abs(1 / 2.0 - 1 / 3.0) / (1 / NEAR - 1 / FAR)  # |1/z - 1/depth_j| over the inverse range
    inner = wrong[0, 3, :, 2:]  # view 1 sits 0.2 m to the right: view 0's first two columns (2 px at 2 m) leave it
    assert torch.allclose(inner, torch.full_like(inner, expected), atol=1e-4), (inner.min(), inner.max(), expected)
    assert (wrong[0, :, :, :2] == 0).all()  # seen by no other view


def test_unknown_depth_gives_zero_consistency():
    sources = dataclasses.replace(wall(), depth=None)
    assert consistency_features(sources, NEAR, FAR).abs().max() == 0


def test_visibility_decreases_along_the_source_ray_and_hit_is_a_probability():
    decoder = VisibilityDecoder(8)
    g = torch.randn(5, 8)
    t = torch.linspace(-1.0, 2.0, 40)
    vis, hit = decoder(g[:, None].expand(5, 39, 8), t[None, :-1].expand(5, -1), t[None, 1:].expand(5, -1))
    assert (vis[:, 1:] <= vis[:, :-1] + 1e-6).all()
    assert ((hit >= 0) & (hit <= 1)).all() and ((vis >= 0) & (vis <= 1)).all()
    # the hits over a partition of the ray are what visibility loses over it
    assert torch.allclose(hit.sum(-1), vis[:, 0] - (vis[:, -1] - hit[:, -1]), atol=1e-5)


def test_a_masked_query_attends_uniformly_and_unmasked_ones_do_not():
    layer = QueryMaskedAttention(8)
    x = torch.randn(1, 5, 8)
    mask = torch.tensor([[True, True, False, True, True]])
    out = layer(x, mask)
    uniform = layer.norm(layer.out(layer.value(x).mean(1, keepdim=True)) + x)
    assert torch.allclose(out[0, 2], uniform[0, 2], atol=1e-6)
    assert not torch.allclose(out[0, 0], uniform[0, 0], atol=1e-4)


def test_the_position_code_alternates_sine_and_cosine():
    code = sinusoidal_code(6, 4, device=torch.device("cpu"), dtype=torch.float32)
    assert torch.allclose(code[:, 0], torch.sin(torch.arange(6.0))) and torch.allclose(code[:, 1], torch.cos(torch.arange(6.0)))
    assert torch.allclose(code[:, 2], torch.sin(torch.arange(6.0) / 100.0))


def test_source_intervals_bracket_each_sample_in_the_source_views_inverse_depth():
    sources = wall()
    rays = RayBatch(origins=torch.zeros(1, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]),
                    pixels=torch.zeros(1, 2), near=torch.full((1,), NEAR), far=torch.full((1,), FAR))
    depths = torch.tensor([[1.0, 2.0, 4.0]])
    low, high = VisibilityAwareRenderer._source_intervals(rays, depths, sources)
    t = normalized_inverse_depth(depths, NEAR, FAR)[..., None].expand(-1, -1, 2)  # camera z = depth in both views
    assert (low < t).all() and (t < high).all()
    assert torch.allclose(high[0, 0], low[0, 1]) and torch.allclose(high[0, 1], low[0, 2])  # intervals tile the ray


@pytest.mark.parametrize("name", ["neuray", "semantic_ray"])
def test_with_a_head_it_renders_features_the_head_decodes_and_without_semantic_maps_it_is_refused(name):
    from gpnerf_core.interfaces.model import SemanticMode
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.testing.inputs import kit_parts, model_batch, model_view

    registry = get_registry()
    node = {"name": name, "coarse_samples": 6, "fine_samples": 4}
    model = registry.build("model", node, parts=kit_parts(registry, name, head=True, parts=KIT_PARTS))
    assert model.semantic_output.mode is SemanticMode.DECODED and model.coarse.aggregator.semantic_out is None
    batch = model_batch(sources=True)
    view = model(batch, semantics=True, sample_semantics=True).views[0]
    rays, channels = batch.views[0].pixels.shape[0], model.extractor.semantic_dim
    assert view.fine.semantic.shape == (rays, channels) and view.fine.sample_semantic.shape == (rays, 4, channels)
    assert view.teacher_at_rays.shape == (rays, channels) and view.logits.shape[1] == model.head.num_outputs
    camera, sources = model_view(sources=True)
    prediction = model.eval().predict(camera, sources, stride=0, chunk_rays=64)
    assert prediction.stride == 2 and prediction.semantic.shape[0] == channels  # the semantic maps' grid, decoded
    assert prediction.logits.shape[-2:] == (camera.height, camera.width)
    parts = kit_parts(registry, name, head=True, parts=KIT_PARTS)
    parts._cfg.model.feature_extractor.semantic = False
    with pytest.raises(Exception, match=r"makes none \(model.feature_extractor.semantic=true, or "):
        registry.build("model", node, parts=parts)


def test_the_kit_fails_a_family_that_says_it_takes_no_head_but_ignores_one():
    class IgnoresHead(model_family.PooledViews):
        capabilities = dataclasses.replace(model_family.PooledViews.capabilities, accepts_head=False)

    def build(*, parts, coarse_samples=8, fine_samples=0, **options):
        return IgnoresHead(extractor=parts.build("feature_extractor"), num_classes=parts.num_classes,
                           coarse_samples=coarse_samples, fine_samples=fine_samples, hidden=8)

    module = types.ModuleType("ignores_head")
    config = dataclasses.make_dataclass("C", [("name", str, "ignores_head")], bases=(model_family.PooledViewsConfig,))
    module.gpnerf_register_models = hookimpl(lambda: [ComponentSpec("ignores_head", build, config)])
    results = check_plugin(module, raise_on_failure=False)
    [build_check] = [r for r in results if r.check == "build"]
    assert build_check.failed and "accepts_head is False but the family built with a configured head" in \
        build_check.message


def test_without_source_depth_it_still_renders_finite_views():
    from gpnerf_core.testing.inputs import kit_parts, model_view
    from gpnerf_core.registry.components import get_registry

    registry = get_registry()
    model = registry.build("model", {"name": "semantic_ray", "coarse_samples": 6, "fine_samples": 4},
                           parts=kit_parts(registry, "semantic_ray", head=False, parts=KIT_PARTS)).eval()
    camera, sources = model_view(sources=True)
    prediction = model.predict(camera, dataclasses.replace(sources, depth=None), stride=4, chunk_rays=50)
    assert torch.isfinite(prediction.rgb).all() and torch.isfinite(prediction.logits).all()
    assert not math.isnan(float(prediction.depth.mean()))


def test_a_whole_view_skips_the_coarse_semantics_without_changing_the_last_pass():
    from gpnerf_core import rays_through_pixels
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.testing.inputs import kit_parts, model_view

    registry = get_registry()
    model = registry.build("model", {"name": "semantic_ray", "coarse_samples": 6, "fine_samples": 4},
                           parts=kit_parts(registry, "semantic_ray", head=False, parts=KIT_PARTS)).eval()
    camera, sources = model_view(sources=True)
    rays = rays_through_pixels(torch.tensor([[3.0, 4.0], [20.0, 11.0]]), camera.intrinsics, camera.c2w, camera.near,
                               camera.far)
    maps = model._stacked(sources, model.encode(sources.rgb), camera)
    with torch.no_grad():
        full_coarse, full = model.render_rays(rays, sources, maps, True, None)
        lean_coarse, lean = model.render_rays(rays, sources, maps, True, None, last_pass_semantics=True)
    assert full_coarse.logits is not None and lean_coarse.logits is None
    assert torch.equal(full.logits, lean.logits) and torch.equal(full.rgb, lean.rgb)
