"""Contract tests run against every registered component of each kind, built with its config defaults.

Third-party plugin authors can run this file against their installed plugin (without
GPNERF_DISABLE_PLUGIN_AUTOLOAD) to check it meets the interfaces.
"""

import dataclasses
import math

import pytest
import torch

from gpnerf_core.geometry import points_along_rays, rays_through_pixels, stratified_inverse_depths
from gpnerf_core.interfaces import (
    FeatureExtractor,
    FieldAggregator,
    LossSet,
    PerceptionHead,
    RayAggregator,
    ViewSelector,
)
from gpnerf_core.registry import get_registry
from gpnerf_core.types import LossInputs, ProjectedFeatures, RenderedRays

REGISTRY = get_registry()


def defaults(kind, name):
    config = REGISTRY.get(kind, name).spec.config
    return {f.name: getattr(config(), f.name) for f in dataclasses.fields(config)}


@pytest.mark.parametrize("name", REGISTRY.names("feature_extractor"))
def test_feature_extractor_contract(name):
    extractor = REGISTRY.build("feature_extractor", defaults("feature_extractor", name))
    assert isinstance(extractor, FeatureExtractor)
    maps = extractor(torch.rand(2, 3, 32, 48))
    assert maps.radiance.shape[:2] == (2, extractor.radiance_dim)
    if extractor.semantic_dim:
        assert maps.semantic.shape[:2] == (2, extractor.semantic_dim)
        assert extractor.semantic_dim % extractor.semantic_levels == 0
    else:
        assert maps.semantic is None


def projected(rays=4, samples=6, views=3, in_dim=35):
    pixels = torch.tensor([[1.0, 2.0], [5.0, 5.0], [9.0, 3.0], [0.0, 0.0]])[:rays]
    K = torch.tensor([[10.0, 0, 5], [0, 10.0, 4], [0, 0, 1]])
    ray_batch = rays_through_pixels(pixels, K, torch.eye(4), 0.5, 4.0)
    samples_ = points_along_rays(ray_batch, stratified_inverse_depths(ray_batch, samples, perturb=False))
    visible = torch.rand(rays, samples, views) > 0.2
    visible[0, 0] = False  # a sample no view sees
    features = ProjectedFeatures(
        rgb_features=torch.randn(rays, samples, views, in_dim),
        semantic=None,
        ray_diff=torch.randn(rays, samples, views, 4),
        visible=visible,
    )
    return features, samples_, ray_batch


@pytest.mark.parametrize("field_name", REGISTRY.names("field_aggregator"))
@pytest.mark.parametrize("ray_name", REGISTRY.names("ray_aggregator"))
def test_aggregators_contract(field_name, ray_name):
    field = REGISTRY.build("field_aggregator", defaults("field_aggregator", field_name), in_dim=35)
    ray = REGISTRY.build("ray_aggregator", defaults("ray_aggregator", ray_name), in_dim=field.width,
                         num_blocks=field.num_blocks)
    assert isinstance(field, FieldAggregator) and isinstance(ray, RayAggregator)
    field.eval(), ray.eval()
    features, samples, rays = projected()
    tokens, context = field.begin(features, samples, rays)
    assert tokens.shape == (4, 6, field.width)
    for index in range(field.num_blocks):
        out = field.block(index, tokens, context)
        assert out.view_attention.shape == (4, 6, 3, field.attention_channels)
        last = ray.block(index, out.tokens)
        assert last.ray_attention.shape == (4, ray.num_heads, 6, 6)
        tokens = last.tokens
    readout = ray.readout(tokens, last)
    assert readout.rgb.shape == (4, 3) and torch.isfinite(readout.rgb).all()
    assert torch.allclose(readout.weights.sum(-1), torch.ones(4), atol=1e-5)


@pytest.mark.parametrize("name", REGISTRY.names("head"))
@pytest.mark.parametrize("classes", [3, 51])
def test_head_contract(name, classes):
    head = REGISTRY.build("head", defaults("head", name), in_dim=64, in_levels=4, num_outputs=classes)
    assert isinstance(head, PerceptionHead) and head.num_outputs == classes
    logits = head(torch.randn(1, 64, 16, 24), (37, 45)).logits
    assert logits.shape == (1, classes, 37, 45)


@pytest.mark.parametrize("name", REGISTRY.names("loss"))
def test_loss_contract(name):
    loss = REGISTRY.build("loss", defaults("loss", name))
    assert isinstance(loss, LossSet)
    rays, samples, channels = 6, 5, 8

    def rendered():
        return RenderedRays(
            rgb=torch.rand(rays, 3, requires_grad=True),
            weights=torch.softmax(torch.randn(rays, samples), -1),
            depth=torch.rand(rays),
            samples=points_along_rays(
                rays_through_pixels(torch.zeros(rays, 2), torch.eye(3), torch.eye(4), 0.5, 2.0),
                torch.linspace(0.5, 2.0, samples).expand(rays, samples),
            ),
            semantic=torch.randn(rays, channels, requires_grad=True),
            sample_semantic=torch.randn(rays, samples, channels, requires_grad=True),
        )

    inputs = LossInputs(
        coarse=rendered(),
        fine=rendered(),
        target_rgb=torch.rand(rays, 3),
        target_depth=torch.rand(rays) + 0.5,
        logits=torch.randn(1, 4, 6, 7, requires_grad=True),
        labels=torch.randint(0, 4, (1, 6, 7)),
        teacher_at_rays=torch.randn(rays, channels),
        ignore_index=255,
    )
    terms = loss(inputs)
    assert terms and all(v.ndim == 0 and math.isfinite(float(v.detach())) for v in terms.values())
    if loss.needs_sample_semantics:
        assert loss.needs_semantics


@pytest.mark.parametrize("name", REGISTRY.names("view_selector"))
def test_view_selector_contract(name):
    selector = REGISTRY.build("view_selector", defaults("view_selector", name))
    assert isinstance(selector, ViewSelector)
    candidates = torch.eye(4).expand(7, 4, 4).clone()
    candidates[:, 0, 3] = torch.arange(7, dtype=torch.float32)
    chosen = selector.select(torch.eye(4), candidates, 3)
    assert chosen == selector.select(torch.eye(4), candidates, 3)
    assert len(set(chosen)) == 3 and all(0 <= c < 7 for c in chosen)
    assert sorted(selector.select(torch.eye(4), candidates[:2], 3)) == [0, 1]
    randomized = selector.select(torch.eye(4), candidates, 3, torch.Generator().manual_seed(0))
    assert len(set(randomized)) == 3
