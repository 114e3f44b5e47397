"""Tests of the resunet_fpn feature extractor."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from gpnerf_core.errors import ConfigError
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_plugins.extractors.extractor import ResUNetFPN, ResUNetFPNConfig
from gpnerf_plugins.extractors.fpn import concat_levels

TINY = dict(widths=[8, 8, 16, 32], blocks=[1, 2, 1], radiance_dim=6, fpn_channels=4)


def _tiny(**overrides) -> ResUNetFPN:
    torch.manual_seed(0)
    return ResUNetFPN(**{**TINY, **overrides})


def test_shapes_and_widths():
    model = _tiny()
    maps = model(torch.rand(2, 3, 32, 48))
    assert maps.radiance.shape == (2, 6, 8, 12)
    assert maps.semantic.shape == (2, 16, 16, 24)
    assert (model.radiance_dim, model.semantic_dim, model.semantic_levels) == (6, 16, 4)
    assert maps.radiance.dtype == maps.semantic.dtype == torch.float32


def test_encoder_taps_strides_and_block_counts():
    model = ResUNetFPN(widths=[8, 8, 16, 32], blocks=[3, 4, 6], fpn_channels=4)
    x0, x1, x2, x3 = model.backbone.encode(torch.rand(1, 3, 32, 48))
    assert [tuple(t.shape[1:]) for t in (x0, x1, x2, x3)] == [(8, 16, 24), (8, 8, 12), (16, 4, 6), (32, 2, 3)]
    assert [len(model.backbone.layer1), len(model.backbone.layer2), len(model.backbone.layer3)] == [3, 4, 6]
    assert not any(isinstance(m, torch.nn.MaxPool2d) for m in model.modules())
    norms = [m for m in model.backbone.modules() if isinstance(m, torch.nn.InstanceNorm2d)]
    assert norms and all(m.affine and not m.track_running_stats for m in norms)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())


def test_default_model_matches_gnt_state_dict_layout():
    model = ResUNetFPN(semantic=False)
    state = model.backbone.state_dict()
    expected = {
        "conv1.weight": (64, 3, 7, 7),
        "layer1.0.downsample.0.weight": (64, 64, 1, 1),
        "layer3.5.conv2.weight": (256, 256, 3, 3),
        "upconv3.conv.conv.weight": (128, 256, 3, 3),
        "iconv3.conv.weight": (128, 256, 3, 3),
        "upconv2.conv.bn.weight": (64,),
        "iconv2.conv.weight": (32, 128, 3, 3),
        "out_conv.weight": (32, 32, 1, 1),
    }
    for key, shape in expected.items():
        assert tuple(state[key].shape) == shape, key
    assert "layer4.0.conv1.weight" not in state


def test_semantic_off_is_radiance_only():
    model = _tiny(semantic=False)
    maps = model(torch.rand(1, 3, 32, 64))
    assert maps.semantic is None
    assert (model.semantic_dim, model.semantic_levels) == (0, 0)
    assert model.fpn is None


@pytest.mark.parametrize("size", [(33, 48), (32, 42), (16, 32)])
def test_bad_image_size_is_a_config_error(size):
    with pytest.raises(ConfigError, match=f"{size[0]}x{size[1]}"):
        _tiny()(torch.rand(1, 3, *size))


@pytest.mark.parametrize(
    "kwargs", [dict(widths=[8, 8, 16]), dict(blocks=[1, 0, 1]), dict(radiance_dim=0), dict(fpn_channels=0)]
)
def test_bad_options_are_config_errors(kwargs):
    with pytest.raises(ConfigError, match="feature_extractor"):
        _tiny(**kwargs)


@pytest.mark.parametrize("detach", [True, False])
def test_detach_flag_controls_radiance_gradient_into_layer3(detach):
    model = _tiny(detach_deep_for_radiance=detach)
    model(torch.rand(1, 3, 32, 32)).radiance.square().sum().backward()
    layer3 = [p.grad for p in model.backbone.layer3.parameters()]
    layer2 = [p.grad for p in model.backbone.layer2.parameters()]
    assert all(g is not None and g.abs().sum() > 0 for g in layer2)  # skip connection still trains layer2
    if detach:
        assert all(g is None for g in layer3)
    else:
        assert all(g is not None for g in layer3) and sum(g.abs().sum() for g in layer3) > 0


def test_semantic_loss_reaches_layer3_even_when_radiance_is_detached():
    model = _tiny(detach_deep_for_radiance=True)
    model(torch.rand(1, 3, 32, 32)).semantic.square().sum().backward()
    assert all(p.grad is not None for p in model.backbone.layer3.parameters())


def test_fpn_levels_sit_in_their_channel_blocks():
    model = _tiny()
    images = torch.rand(1, 3, 32, 48)
    taps = list(model.backbone.encode(images))
    levels = model.fpn(taps)
    semantic = model(images).semantic
    c = 4
    assert [tuple(x.shape[-2:]) for x in levels] == [(16, 24), (8, 12), (4, 6), (2, 3)]
    for k, level in enumerate(levels):
        expected = level if k == 0 else F.interpolate(level, size=(16, 24), mode="bilinear", align_corners=True)
        torch.testing.assert_close(semantic[:, k * c : (k + 1) * c], expected)

    # Perturbing the finest tap changes only block 0 (the top-down path runs coarse to fine).
    perturbed = concat_levels(model.fpn([taps[0] + 1.0, *taps[1:]]))
    changed = [(perturbed - semantic)[:, k * c : (k + 1) * c].abs().max() > 1e-4 for k in range(4)]
    assert changed == [True, False, False, False]
    # Perturbing the coarsest tap changes every block.
    perturbed = concat_levels(model.fpn([*taps[:3], taps[3] + 1.0]))
    assert all((perturbed - semantic)[:, k * c : (k + 1) * c].abs().max() > 1e-4 for k in range(4))
    # Shifting one level's output conv moves exactly its block.
    with torch.no_grad():
        model.fpn.fpn_convs[2].bias += 0.5
    shifted = model(images).semantic
    expected = torch.zeros(1, 16, 16, 24)
    expected[:, 8:12] = 0.5
    torch.testing.assert_close(shifted - semantic, expected)


def test_semantic_outputs_are_signed():
    semantic = _tiny()(torch.rand(1, 3, 32, 32)).semantic
    assert semantic.min() < 0 < semantic.max()


def test_deterministic_given_seed():
    images = torch.rand(1, 3, 32, 32)
    a, b = _tiny()(images), _tiny()(images)
    torch.testing.assert_close(a.radiance, b.radiance)
    torch.testing.assert_close(a.semantic, b.semantic)


def test_registered_and_buildable_from_structured_config():
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.extractors.plugin",), autoload=False))
    assert not registry.problems
    entry = registry.get("feature_extractor", "resunet_fpn")
    assert entry.spec.config is ResUNetFPNConfig
    node = OmegaConf.structured(ResUNetFPNConfig)
    node.widths = [8, 8, 16, 32]
    node.blocks = [1, 1, 1]
    node.fpn_channels = 4
    model = registry.build("feature_extractor", node)
    assert isinstance(model, ResUNetFPN) and model.semantic_dim == 16
    defaults = {f.name for f in dataclasses.fields(ResUNetFPNConfig)}
    assert defaults == {
        "name", "widths", "blocks", "radiance_dim", "detach_deep_for_radiance", "semantic", "fpn_channels"
    }


def test_sides_that_are_not_multiples_of_16_are_padded_and_the_maps_cropped_to_tile_the_image():
    """120x160 (half-resolution ScanNet) and the like: maps of exactly H/4 x W/4 and H/2 x W/2 cells."""
    model = _tiny().eval()
    image = torch.rand(1, 3, 40, 56)
    maps = model(image)
    assert maps.radiance.shape == (1, 6, 10, 14) and maps.semantic.shape == (1, 16, 20, 28)
    padded = model(torch.nn.functional.pad(image, (0, 8, 0, 8), mode="replicate"))
    assert torch.equal(maps.radiance, padded.radiance[..., :10, :14])
    assert torch.equal(maps.semantic, padded.semantic[..., :20, :28])
