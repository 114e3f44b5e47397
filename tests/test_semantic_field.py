import pytest
import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.semantic_field import SemanticFieldRenderer


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
