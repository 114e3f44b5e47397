"""The source-feature cache: cached and uncached renders are equal, each source frame is encoded once per model
state, a weight change is never served stale features, and the budget evicts least recently used frames."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.data.frames import FrameCache, choose_sources
from pipeline_check import TINY_MODEL, TINY_SCENES


@pytest.fixture(scope="module")
def setup():
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, "model.num_source_views=3"])
    torch.manual_seed(0)
    components = build_components(cfg)
    model = components.model.eval()
    frames = FrameCache(components.dataset, torch.device("cpu"))
    scene = frames.scene(components.dataset.scenes("train")[0])
    return model, frames, scene, components.view_selector


def views(setup):
    model, frames, scene, selector = setup
    for target in scene.eval_frames + scene.train_frames[:3]:
        chosen = choose_sources(selector, scene, target, 3, None)
        yield target, chosen, frames.source_views(scene, chosen), frames.camera(scene, frames.frame(scene, target))


def test_cached_renders_equal_uncached_ones_and_each_frame_is_encoded_once(setup):
    model = setup[0]
    cache = SourceFeatureCache(budget_mb=64)
    requested = set()
    for _, chosen, sources, camera in views(setup):
        plain = model.predict(camera, sources, stride=0, chunk_rays=256)
        cached = model.predict(camera, sources, stride=0, chunk_rays=256,
                               features=cache.features(model, setup[2].name, chosen, sources.rgb))
        # batched convolutions of another batch composition reassociate sums: equal up to float32 rounding (~1e-5 on
        # colour and depth, 1e-5 on rendered features, amplified to ~1e-4 in the logits); the same classes everywhere
        for name, tolerance in (("rgb", 1e-4), ("depth", 1e-4), ("semantic", 1e-4), ("logits", 1e-3)):
            difference = (getattr(cached, name) - getattr(plain, name)).abs().max()
            assert difference < tolerance, (name, float(difference))
        assert torch.equal(cached.logits.argmax(1), plain.logits.argmax(1))
        requested |= set(chosen)
    assert cache.stats.misses == len(requested) and cache.stats.hits > 0  # every frame encoded exactly once


def test_a_weight_change_is_never_served_old_features(setup):
    model, _, scene, _ = setup
    target, chosen, sources, camera = next(views(setup))
    cache = SourceFeatureCache(budget_mb=64)
    before = cache.features(model, scene.name, chosen, sources.rgb)
    with torch.no_grad():
        parameter = next(model.parameters())
        parameter.add_(0.5)
    try:
        after = cache.features(model, scene.name, chosen, sources.rgb)
        assert cache.stats.misses == 2 * len(chosen)
        assert not torch.allclose(after.radiance, before.radiance)
        assert torch.allclose(after.radiance, model.encode(sources.rgb).radiance, atol=1e-5)
    finally:
        with torch.no_grad():
            parameter.sub_(0.5)


def test_the_budget_evicts_least_recently_used_frames(setup):
    model, _, scene, _ = setup
    _, chosen, sources, _ = next(views(setup))
    one = SourceFeatureCache(budget_mb=64)
    one.features(model, scene.name, chosen[:1], sources.rgb[:1])
    frame_bytes = one.stats.bytes
    cache = SourceFeatureCache(budget_mb=2.5 * frame_bytes / 2**20)  # room for two frames
    cache.features(model, scene.name, chosen[:2], sources.rgb[:2])
    cache.features(model, scene.name, chosen[2:3], sources.rgb[2:3])
    assert len(cache) == 2 and cache.stats.bytes <= cache.budget
    cache.features(model, scene.name, chosen[1:3], sources.rgb[1:3])  # both still there: no encoding
    assert cache.stats.misses == 3
    with pytest.raises(ConfigError, match="budget"):
        SourceFeatureCache(budget_mb=0)


class SetEncoder(torch.nn.Module):
    """A family that encodes its source views together (``SourceEncoding.SOURCE_SET``), counting its encodings."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.ones(1))
        self.calls = 0

    @property
    def capabilities(self):
        from gpnerf_core.interfaces.model import Capabilities, SourceEncoding

        return Capabilities(source_encoding=SourceEncoding.SOURCE_SET)

    def encode_sources(self, sources, *, near, far):
        self.calls += 1
        return {"mean": sources.rgb.mean(0) * self.weight, "bounds": torch.tensor([near, far])}


def test_a_source_set_is_encoded_once_per_set_model_state_and_bounds(setup):
    _, _, scene, _ = setup
    _, chosen, sources, _ = next(views(setup))
    model, cache = SetEncoder(), SourceFeatureCache(budget_mb=64)
    first = cache.for_sources(model, scene.name, chosen, sources, near=0.5, far=4.0)
    again = cache.for_sources(model, scene.name, chosen, sources, near=0.5, far=4.0)
    assert again is first and model.calls == 1 and (cache.stats.hits, cache.stats.misses) == (1, 1)
    assert cache.stats.bytes == first["mean"].numel() * 4 + 2 * 4  # every tensor inside is counted
    reordered = [chosen[1], chosen[0], *chosen[2:]]
    cache.for_sources(model, scene.name, reordered, sources, near=0.5, far=4.0)
    cache.for_sources(model, scene.name, chosen, sources, near=0.5, far=5.0)
    with torch.no_grad():
        model.weight.mul_(2.0)
    fresh = cache.for_sources(model, scene.name, chosen, sources, near=0.5, far=4.0)
    assert model.calls == 4 and torch.allclose(fresh["mean"], 2 * first["mean"])
    with pytest.raises(ConfigError, match="2 frame indices for 3 source views"):
        cache.for_sources(model, scene.name, chosen[:2], sources, near=0.5, far=4.0)
