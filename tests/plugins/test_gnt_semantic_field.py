import pytest
import torch

from gpnerf_core.errors import ConfigError
from gpnerf_plugins.families.gnt.semantic_field import SemanticFieldRenderer


def attentions(rays, samples, views, channels, heads, blocks, seed=0):
    g = torch.Generator().manual_seed(seed)
    view = [torch.softmax(torch.randn(rays, samples, views, channels, generator=g), dim=2) for _ in range(blocks)]
    ray = [torch.softmax(torch.randn(rays, heads, samples, samples, generator=g), dim=-1) for _ in range(blocks)]
    return view, ray


@pytest.mark.parametrize("channels,attention,heads", [(64, 32, 4), (512, 64, 4), (24, 8, 2)])
def test_one_pass_equals_block_by_block(channels, attention, heads):
    renderer = SemanticFieldRenderer(semantic_dim=channels, attention_channels=attention, ray_heads=heads, num_blocks=3)
    semantic = torch.randn(5, 7, 3, channels, dtype=torch.float64)
    view, ray = attentions(5, 7, 3, attention, heads, 3)
    view, ray = [v.double() for v in view], [r.double() for r in ray]
    renderer = renderer.double()
    grouped = semantic.reshape(5, 7, 3, attention, channels // attention)
    fast = torch.einsum("rsvae,rsva->rae", grouped, renderer.combined_weights(view, ray)).reshape(5, channels)
    assert torch.allclose(fast, renderer.reference_forward(semantic, view, ray), atol=1e-10)


def test_adaptor_starts_as_block_mean_so_constant_features_render_unchanged():
    renderer = SemanticFieldRenderer(semantic_dim=16, attention_channels=8, ray_heads=4, num_blocks=4)
    feature = torch.randn(16)
    semantic = feature.expand(3, 5, 2, 16).contiguous()
    view, ray = attentions(3, 5, 2, 8, 4, 4)
    rendered, per_sample = renderer(semantic, view, ray, with_samples=True)
    assert torch.allclose(rendered, feature.expand(3, 16), atol=1e-5)
    assert torch.allclose(per_sample, 4 * feature.expand(3, 5, 16), atol=1e-5)


def test_frozen_attention_blocks_gradient_to_attention():
    for joint in (True, False):
        renderer = SemanticFieldRenderer(
            semantic_dim=16, attention_channels=8, ray_heads=4, num_blocks=2, joint_attention=joint
        )
        view, ray = attentions(2, 4, 3, 8, 4, 2)
        view = [v.requires_grad_() for v in view]
        ray = [r.requires_grad_() for r in ray]
        rendered, per_sample = renderer(torch.randn(2, 4, 3, 16), view, ray, with_samples=True)
        (rendered.sum() + per_sample.sum()).backward()
        assert (view[0].grad is not None) == joint and (ray[1].grad is not None) == joint


def test_incompatible_widths_are_config_errors():
    with pytest.raises(ConfigError, match="multiple of the view attention"):
        SemanticFieldRenderer(semantic_dim=60, attention_channels=32, ray_heads=4, num_blocks=2)
    with pytest.raises(ConfigError, match="heads"):
        SemanticFieldRenderer(semantic_dim=64, attention_channels=32, ray_heads=5, num_blocks=2)


def sampled_maps(rays, samples, views, channels, seed=0, dtype=torch.float64):
    """Random maps and grid coordinates, some outside the maps (zeros there)."""
    from gpnerf_core.types import SampledMaps

    g = torch.Generator().manual_seed(seed)
    maps = torch.randn(views, channels, 6, 8, generator=g, dtype=dtype)
    grid = (torch.rand(views, rays * samples, 1, 2, generator=g, dtype=dtype) * 2.4 - 1.2)
    return SampledMaps(maps, grid, rays, samples)


@pytest.mark.parametrize("with_samples", [False, True])
@pytest.mark.parametrize("recompute", [False, True])
@pytest.mark.parametrize("joint", [True, False])
def test_streamed_rendering_equals_dense_forward_and_gradients(with_samples, recompute, joint):
    """Streaming F view by view computes what the dense einsum computes: outputs and every attention gradient."""
    rays, samples, views, channels, attention, heads, blocks = 5, 7, 3, 32, 8, 2, 3
    renderer = SemanticFieldRenderer(
        semantic_dim=channels, attention_channels=attention, ray_heads=heads, num_blocks=blocks, joint_attention=joint
    ).double()
    sampled = sampled_maps(rays, samples, views, channels)
    results = []
    for streamed in (True, False):
        view, ray = attentions(rays, samples, views, attention, heads, blocks, seed=1)
        view = [v.double().requires_grad_() for v in view]
        ray = [r.double().requires_grad_() for r in ray]
        semantic = sampled if streamed else sampled.dense()
        rendered, per_sample = renderer(semantic, view, ray, with_samples=with_samples, recompute_samples=recompute)
        g = torch.Generator().manual_seed(2)
        loss = (rendered * torch.randn(rendered.shape, generator=g, dtype=torch.float64)).sum()
        if with_samples:
            loss = loss + (per_sample * torch.randn(per_sample.shape, generator=g, dtype=torch.float64)).sum()
        loss.backward()
        grads = [t.grad for t in view + ray]
        results.append((rendered.detach(), per_sample, grads))
    (fast, fast_samples, fast_grads), (slow, slow_samples, slow_grads) = results
    assert torch.allclose(fast, slow, atol=1e-12)
    if with_samples:
        assert torch.allclose(fast_samples.detach(), slow_samples.detach(), atol=1e-12)
    else:
        assert fast_samples is None and slow_samples is None
    for a, b in zip(fast_grads, slow_grads, strict=True):
        assert (a is None) == (b is None) == (not joint)
        if a is not None:
            assert torch.allclose(a, b, atol=1e-12)


def test_streamed_rendering_passes_gradcheck():
    from gpnerf_plugins.families.gnt.semantic_field import StreamedRendering

    sampled = sampled_maps(3, 4, 2, 8)
    weights = torch.rand(3, 4, 2, 4, dtype=torch.float64, requires_grad=True)
    sample_weights = torch.rand(3, 4, 2, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda w, s: StreamedRendering.apply(w, s, sampled, 2, True), (weights, sample_weights)
    )


def test_source_maps_with_gradients_take_the_dense_path_and_receive_gradients():
    from gpnerf_core.types import SampledMaps

    renderer = SemanticFieldRenderer(semantic_dim=16, attention_channels=8, ray_heads=4, num_blocks=2).double()
    base = sampled_maps(2, 4, 3, 16)
    maps = base.maps.clone().requires_grad_()
    view, ray = attentions(2, 4, 3, 8, 4, 2)
    rendered, _ = renderer(SampledMaps(maps, base.grid, 2, 4), [v.double() for v in view], [r.double() for r in ray])
    rendered.sum().backward()
    assert maps.grad is not None and maps.grad.abs().sum() > 0


def test_streamed_rendering_mixes_bf16_attention_with_fp32_maps():
    """Under autocast the attention may be bf16 and the maps fp32: outputs promote, gradients keep their dtype."""
    renderer = SemanticFieldRenderer(semantic_dim=16, attention_channels=8, ray_heads=4, num_blocks=2)
    sampled = sampled_maps(2, 4, 3, 16, dtype=torch.float32)
    view, ray = attentions(2, 4, 3, 8, 4, 2)
    view = [v.bfloat16().requires_grad_() for v in view]
    ray = [r.bfloat16().requires_grad_() for r in ray]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rendered, per_sample = renderer(sampled, view, ray, with_samples=True)
        dense, _ = renderer(sampled.dense(), view, ray, with_samples=True)
    assert torch.allclose(rendered.float(), dense.float(), atol=5e-2)
    (rendered.float().sum() + per_sample.float().sum()).backward()
    assert view[0].grad.dtype == torch.bfloat16 and ray[0].grad.dtype == torch.bfloat16


def test_streamed_rendering_reads_each_view_s_weights_contiguously(monkeypatch):
    """The per-view products read the weights as contiguous [A, 1, R, S] slices: a permuted view of [R, S, V, A]
    (what ``.to(dtype, memory_format=...)`` returns when the dtype matches) made a rendered view 5x slower there."""
    from gpnerf_plugins.families.gnt.semantic_field import StreamedRendering

    rays, samples, views, channels, attention = 4, 6, 3, 16, 8
    seen = []
    vecdot = torch.linalg.vecdot

    def recording(x, y, *, dim=-1):
        seen.append(y.squeeze(1).is_contiguous())
        return vecdot(x, y, dim=dim)

    monkeypatch.setattr(torch.linalg, "vecdot", recording)
    weights = torch.rand(rays, samples, views, attention)
    StreamedRendering.apply(weights, None, sampled_maps(rays, samples, views, channels, dtype=torch.float32),
                            channels // attention, True)
    assert seen == [True] * views


def test_streamed_rendering_returns_its_weight_gradients_in_the_weights_own_layout():
    """Gradients leave the backward as contiguous ``[R, S, V, A]``, the layout of the attention they are added to: a
    permuted ``[V, A, R, S]`` gradient made every later product and sum of the transformers' backward stride through
    memory (the paper-size training step 6.0 -> 5.2 s when fixed, the same values bit for bit)."""
    from gpnerf_plugins.families.gnt.semantic_field import StreamedRendering

    rays, samples, views, channels, attention = 4, 6, 3, 16, 8
    weights = torch.rand(rays, samples, views, attention, requires_grad=True)
    sample_weights = torch.rand(rays, samples, views, attention, requires_grad=True)
    rendered, per_sample = StreamedRendering.apply(
        weights, sample_weights, sampled_maps(rays, samples, views, channels, dtype=torch.float32),
        channels // attention, True)
    grads = torch.autograd.grad((rendered.sum() + per_sample.square().sum()), (weights, sample_weights))
    for grad in grads:
        assert grad.shape == weights.shape and grad.is_contiguous()
