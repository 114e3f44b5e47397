"""Tests of the unet and per_pixel perception heads."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from gpnerf_core.errors import ConfigError
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_plugins.extractors.fpn import concat_levels
from gpnerf_plugins.heads.per_pixel import PerPixelHead, PerPixelHeadConfig
from gpnerf_plugins.heads.unet import ConvGNReLU, UNetHead, UNetHeadConfig, split_levels


def _head(kind: str, num_outputs: int, in_dim: int = 32, **kwargs):
    torch.manual_seed(0)
    if kind == "per_pixel":
        return PerPixelHead(in_dim=in_dim, in_levels=4, num_outputs=num_outputs, hidden_dim=16, **kwargs)
    return UNetHead(
        in_dim=in_dim, in_levels=4, num_outputs=num_outputs, decoder=kind, channels=16, norm_groups=4, **kwargs
    )


KINDS = ["unet", "semantic_fpn", "per_pixel"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("num_outputs", [3, 51])
@pytest.mark.parametrize("map_size", [(16, 24), (15, 22)])
def test_logits_have_requested_size_and_classes(kind, num_outputs, map_size):
    head = _head(kind, num_outputs)
    out = head(torch.randn(2, 32, *map_size), output_size=(37, 53))
    assert out.logits.shape == (2, num_outputs, 37, 53)
    assert head.num_outputs == num_outputs
    assert torch.isfinite(out.logits).all()


@pytest.mark.parametrize("kind", KINDS)
def test_same_size_output_skips_resizing_and_gradient_reaches_input(kind):
    head = _head(kind, 5)
    features = torch.randn(1, 32, 8, 12, requires_grad=True)
    logits = head(features, output_size=(8, 12)).logits
    assert logits.shape == (1, 5, 8, 12)
    logits.square().mean().backward()
    assert features.grad is not None and features.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", ["unet", "semantic_fpn"])
def test_chunk_width_equal_to_channels(kind):
    head = UNetHead(in_dim=64, in_levels=4, num_outputs=4, decoder=kind, channels=16, norm_groups=8)
    assert head(torch.randn(1, 64, 16, 16), (16, 16)).logits.shape == (1, 4, 16, 16)


def test_single_level_map():
    for decoder in ("unet", "semantic_fpn"):
        head = UNetHead(in_dim=6, in_levels=1, num_outputs=2, decoder=decoder, channels=4, norm_groups=2)
        assert head(torch.randn(1, 6, 5, 7), (9, 9)).logits.shape == (1, 2, 9, 9)


def test_semantic_fpn_has_one_plus_one_plus_two_plus_three_convs():
    head = UNetHead(in_dim=32, in_levels=4, num_outputs=3, decoder="semantic_fpn", channels=16, norm_groups=4)
    assert [len(h) for h in head.decoder.scale_heads] == [1, 1, 2, 3]
    assert sum(isinstance(m, ConvGNReLU) for m in head.modules()) == 7


def _ramp(height: int, width: int, slope_y: float, slope_x: float) -> torch.Tensor:
    """A map linear in the corner-aligned normalised image coordinates, ``[1, 1, height, width]``."""
    y = torch.linspace(-1.0, 1.0, height)[:, None]
    x = torch.linspace(-1.0, 1.0, width)[None, :]
    return (slope_y * y + slope_x * x)[None, None]


def test_split_levels_undoes_the_extractor_concat_geometry():
    levels = [_ramp(16 // 2**k, 24 // 2**k, 1.0 + k, 2.0 - k) for k in range(4)]
    restored = split_levels(concat_levels(levels), 4)
    for original, back in zip(levels, restored):
        torch.testing.assert_close(back, original, atol=1e-5, rtol=1e-5)
    # The blocks come back in order: block k carries level k's slopes.
    for k, back in enumerate(restored):
        assert torch.allclose(back[0, 0, -1, 0] - back[0, 0, 0, 0], torch.tensor(2.0 * (1.0 + k)))


def test_split_levels_rounds_odd_sizes_up():
    sizes = [tuple(x.shape[-2:]) for x in split_levels(torch.randn(1, 8, 15, 22), 4)]
    assert sizes == [(15, 22), (8, 11), (4, 6), (2, 3)]


def _far_corner_change(kind: str) -> float:
    head = _head(kind, 3).eval()
    features = torch.randn(1, 32, 16, 16)
    perturbed = features.clone()
    perturbed[:, :, 0, 0] += 5.0
    with torch.no_grad():
        a = head(features, (16, 16)).logits
        b = head(perturbed, (16, 16)).logits
    return float((a - b)[..., 8:, 8:].abs().max())


def test_per_pixel_head_has_no_spatial_context():
    assert _far_corner_change("per_pixel") == 0.0


@pytest.mark.parametrize("kind", ["unet", "semantic_fpn"])
def test_context_heads_see_far_cells(kind):
    assert _far_corner_change(kind) > 1e-6


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(decoder="fpn"), "unet, semantic_fpn"),
        (dict(norm_groups=5), "norm_groups=5"),
        (dict(channels=0), "channels=0"),
        (dict(in_dim=30), "in_dim=30"),
        (dict(num_outputs=0), "num_outputs=0"),
        (dict(in_dim=0, in_levels=0), "semantic feature map"),
    ],
)
def test_unet_head_bad_options(kwargs, match):
    options = dict(in_dim=32, in_levels=4, num_outputs=3, decoder="unet", channels=16, norm_groups=4)
    with pytest.raises(ConfigError, match=match):
        UNetHead(**{**options, **kwargs})


def test_per_pixel_bad_options_and_linear_variant():
    with pytest.raises(ConfigError, match="hidden_layers"):
        PerPixelHead(in_dim=8, in_levels=1, num_outputs=2, hidden_layers=-1)
    linear = PerPixelHead(in_dim=8, in_levels=1, num_outputs=2, hidden_layers=0)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in linear.modules()) == 1


@pytest.mark.parametrize("kind", KINDS)
def test_wrong_input_is_a_config_error(kind):
    head = _head(kind, 3)
    with pytest.raises(ConfigError, match="in_dim=32"):
        head(torch.randn(1, 16, 8, 8), (8, 8))
    with pytest.raises(ConfigError, match="output_size"):
        head(torch.randn(1, 32, 8, 8), (0, 8))


def test_registered_and_buildable_from_structured_config():
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.heads.plugin",), autoload=False))
    assert not registry.problems and registry.names("head") == ["instance", "per_pixel", "unet"]
    node = OmegaConf.structured(UNetHeadConfig)
    node.channels, node.norm_groups, node.decoder = 8, 2, "semantic_fpn"
    head = registry.build("head", node, in_dim=16, in_levels=4, num_outputs=7)
    assert isinstance(head, UNetHead) and head.decoder_kind == "semantic_fpn"
    assert head(torch.randn(1, 16, 8, 8), (16, 16)).logits.shape == (1, 7, 16, 16)
    per_pixel = registry.build("head", OmegaConf.structured(PerPixelHeadConfig), in_dim=16, in_levels=4, num_outputs=7)
    assert isinstance(per_pixel, PerPixelHead)
