"""Tests of the GNT view transformer (``gnt_view``) and ray transformer (``gnt_ray``) plugins."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.interfaces import FieldAggregator, RayAggregator
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_core.types import ProjectedFeatures, RayBatch, RaySamples
from gpnerf_plugins.transformers import (
    GNTRayTransformer,
    GNTViewTransformer,
    split_gnt_state_dict,
)
from gpnerf_plugins.transformers import common
from gpnerf_plugins.transformers.common import masking_value, positional_encoding

R, S, V, D, BLOCKS, IN_DIM, FREQS = 5, 7, 3, 16, 2, 11, 4


def make_inputs(seed: int = 0, dtype: torch.dtype = torch.float32):
    """Random projected features with some hidden views; sample (0, 0) is seen by no view."""
    g = torch.Generator().manual_seed(seed)
    rgb_features = torch.randn(R, S, V, IN_DIM, generator=g, dtype=dtype)
    ray_diff = torch.randn(R, S, V, 4, generator=g, dtype=dtype)
    visible = torch.rand(R, S, V, generator=g) > 0.3
    visible[0, 0] = False
    visible[1, :, 0] = True
    features = ProjectedFeatures(rgb_features=rgb_features, semantic=None, ray_diff=ray_diff, visible=visible)
    depths = torch.linspace(1.0, 3.0, S, dtype=dtype).expand(R, S)
    origins = torch.randn(R, 3, generator=g, dtype=dtype)
    directions = torch.randn(R, 3, generator=g, dtype=dtype)
    points = origins[:, None] + depths[..., None] * directions[:, None]
    rays = RayBatch(origins, directions, torch.zeros(R, 2), torch.ones(R), torch.full((R,), 4.0))
    return features, RaySamples(depths=depths, points=points), rays


def build(dropout: float = 0.0, seed: int = 0) -> tuple[GNTViewTransformer, GNTRayTransformer]:
    torch.manual_seed(seed)
    field = GNTViewTransformer(in_dim=IN_DIM, width=D, num_blocks=BLOCKS, dropout=dropout, pos_frequencies=FREQS)
    ray = GNTRayTransformer(in_dim=field.width, num_blocks=field.num_blocks, num_heads=4, dropout=dropout)
    return field, ray


def run(field: GNTViewTransformer, ray: GNTRayTransformer, inputs) -> dict:
    """The pipeline's interleaving of the two aggregators."""
    tokens, ctx = field.begin(*inputs)
    view_attention, ray_attention = [], []
    for b in range(field.num_blocks):
        out = field.block(b, tokens, ctx)
        rout = ray.block(b, out.tokens)
        tokens = rout.tokens
        view_attention.append(out.view_attention)
        ray_attention.append(rout.ray_attention)
    readout = ray.readout(tokens, rout)
    return {"tokens": tokens, "rgb": readout.rgb, "weights": readout.weights,
            "view_attention": view_attention, "ray_attention": ray_attention}


# --- A literal GNT transformer, written from the reference facts with GNT's module names ------------------


class _RefFF(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, 4 * dim), nn.Linear(4 * dim, dim)

    def forward(self, x):
        return self.fc2(torch.relu(self.fc1(x)))


class _RefViewAttn(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.q_fc, self.k_fc, self.v_fc = (nn.Linear(dim, dim, bias=False) for _ in range(3))
        self.pos_fc = nn.Sequential(nn.Linear(4, dim // 8), nn.ReLU(), nn.Linear(dim // 8, dim))
        self.attn_fc = nn.Sequential(nn.Linear(dim, dim // 8), nn.ReLU(), nn.Linear(dim // 8, dim))
        self.out_fc = nn.Linear(dim, dim)

    def forward(self, q, f, ray_diff, mask):
        q, k = self.q_fc(q), self.k_fc(f)
        v, pos = self.v_fc(k), self.pos_fc(ray_diff)
        logits = self.attn_fc(k - q[:, :, None] + pos).masked_fill(~mask[..., None], -1e9)
        attn = torch.softmax(logits, dim=2)
        return self.out_fc(((v + pos) * attn).sum(dim=2)), attn


class _RefRayAttn(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.q_fc, self.k_fc, self.v_fc = (nn.Linear(dim, dim, bias=False) for _ in range(3))
        self.out_fc = nn.Linear(dim, dim)
        self.heads = heads

    def forward(self, x):
        r, s, d = x.shape
        split = lambda t: t.view(r, s, self.heads, -1).permute(0, 2, 1, 3)  # noqa: E731
        q, k, v = split(self.q_fc(x)), split(self.k_fc(x)), split(self.v_fc(x))
        attn = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(d // self.heads), dim=-1)
        return self.out_fc((attn @ v).permute(0, 2, 1, 3).reshape(r, s, d)), attn


class _RefBlock(nn.Module):
    def __init__(self, dim, attn):
        super().__init__()
        self.attn_norm, self.ff_norm = nn.LayerNorm(dim, eps=1e-6), nn.LayerNorm(dim, eps=1e-6)
        self.ff, self.attn = _RefFF(dim), attn

    def forward(self, x, *args):
        out, attn = self.attn(self.attn_norm(x), *args)
        x = x + out
        return x + self.ff(self.ff_norm(x)), attn


class _RefGNT(nn.Module):
    def __init__(self, in_dim, dim, blocks, freqs):
        super().__init__()
        enc = 3 + 6 * freqs
        self.freqs = freqs
        self.rgbfeat_fc = nn.Sequential(nn.Linear(in_dim, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.view_crosstrans = nn.ModuleList(_RefBlock(dim, _RefViewAttn(dim)) for _ in range(blocks))
        self.view_selftrans = nn.ModuleList(_RefBlock(dim, _RefRayAttn(dim, 4)) for _ in range(blocks))
        self.q_fcs = nn.ModuleList(
            nn.Sequential(nn.Linear(dim + 2 * enc, dim), nn.ReLU(), nn.Linear(dim, dim))
            if i % 2 == 0
            else nn.Identity()
            for i in range(blocks)
        )
        self.norm, self.rgb_fc = nn.LayerNorm(dim), nn.Linear(dim, 3)
        self.semantic_adaptor = nn.Sequential(nn.Linear(8, 8), nn.ReLU())  # GP-NeRF extra, not ours

    def encode(self, x):
        parts = [x]
        for i in range(self.freqs):
            parts += [torch.sin(x * 2.0**i), torch.cos(x * 2.0**i)]
        return torch.cat(parts, dim=-1)

    def forward(self, rgb_feat, ray_diff, mask, pts, ray_d):
        dirs = self.encode(ray_d / ray_d.norm(dim=-1, keepdim=True))[:, None].expand(-1, pts.shape[1], -1)
        pts = self.encode(pts)
        f = self.rgbfeat_fc(rgb_feat)
        q = f.max(dim=2)[0]
        view_attns, ray_attns = [], []
        for i in range(len(self.view_crosstrans)):
            q, a = self.view_crosstrans[i](q, f, ray_diff, mask)
            if i % 2 == 0:
                q = self.q_fcs[i](torch.cat((q, pts, dirs), dim=-1))
            q, r = self.view_selftrans[i](q)
            view_attns.append(a)
            ray_attns.append(r)
        rgb = self.rgb_fc(self.norm(q).mean(dim=1))
        return rgb, ray_attns[-1].mean(dim=1)[:, 0], view_attns, ray_attns


def test_matches_literal_gnt_and_loads_its_state_dict():
    torch.manual_seed(1)
    ref = _RefGNT(IN_DIM, D, BLOCKS, FREQS).double().eval()
    with torch.no_grad():
        for p in ref.parameters():  # move LayerNorms and biases away from their trivial init
            p.add_(0.1 * torch.randn_like(p))
    field, ray = build()
    field, ray = field.double().eval(), ray.double().eval()
    parts = split_gnt_state_dict({"module." + k: v for k, v in ref.state_dict().items()})
    field.load_state_dict(parts.field, strict=True)
    ray.load_state_dict(parts.ray, strict=True)
    assert set(parts.unused) == {"module.semantic_adaptor.0.weight", "module.semantic_adaptor.0.bias"}

    inputs = make_inputs(dtype=torch.float64)
    features, samples, rays = inputs
    ours = run(field, ray, inputs)
    rgb, weights, view_attns, ray_attns = ref(
        features.rgb_features, features.ray_diff, features.visible, samples.points, rays.directions
    )
    torch.testing.assert_close(ours["rgb"], rgb, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(ours["weights"], weights, rtol=1e-9, atol=1e-9)
    for a, b in zip(ours["view_attention"] + ours["ray_attention"], view_attns + ray_attns):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)

    # Same gradients for every GNT parameter from a loss on colour and on every attention map.
    probes = [torch.randn_like(a) for a in view_attns + ray_attns]
    for out, attns in ((ours["rgb"], ours["view_attention"] + ours["ray_attention"]), (rgb, view_attns + ray_attns)):
        (out.square().sum() + sum((a * p).sum() for a, p in zip(attns, probes))).backward()
    ref_grads = split_gnt_state_dict({k: p.grad for k, p in ref.named_parameters()})
    for module, grads in ((field, ref_grads.field), (ray, ref_grads.ray)):
        for name, p in module.named_parameters():
            torch.testing.assert_close(p.grad, grads[name], rtol=1e-7, atol=1e-9, msg=name)


# --- Properties ---------------------------------------------------------------------------------------


def test_shapes_and_interface():
    field, ray = build()
    assert isinstance(field, FieldAggregator) and isinstance(ray, RayAggregator)
    assert (field.width, field.attention_channels, field.num_blocks) == (D, D, BLOCKS)
    assert (ray.num_heads, ray.num_blocks) == (4, BLOCKS)
    inputs = make_inputs()
    tokens, ctx = field.begin(*inputs)
    assert tokens.shape == (R, S, D)
    assert ctx.view_features.shape == (R, S, V, D)
    assert ctx.point_encoding.shape == (R, S, 3 + 6 * FREQS)
    assert ctx.direction_encoding.shape == (R, 3 + 6 * FREQS)
    out = run(field, ray, inputs)
    assert out["tokens"].shape == (R, S, D)
    assert out["rgb"].shape == (R, 3) and out["weights"].shape == (R, S)
    assert all(a.shape == (R, S, V, D) for a in out["view_attention"])
    assert all(a.shape == (R, 4, S, S) for a in out["ray_attention"])


def test_attention_normalised_and_masked():
    field, ray = build(dropout=0.0)
    features = make_inputs()[0]
    out = run(field.train(), ray.train(), make_inputs())  # dropout 0: training mode changes nothing
    for a in out["view_attention"]:
        torch.testing.assert_close(a.sum(dim=2), torch.ones(R, S, D))
        seen_by_some = features.visible.any(dim=-1)
        hidden = ~features.visible & seen_by_some[..., None]
        assert hidden.any()
        assert a[hidden].abs().max() < 1e-6
        # A sample no view sees gets uniform, finite weights rather than NaN.
        torch.testing.assert_close(a[0, 0], torch.full((V, D), 1.0 / V))
    for a in out["ray_attention"]:
        torch.testing.assert_close(a.sum(dim=-1), torch.ones(R, 4, S))
    torch.testing.assert_close(out["weights"].sum(dim=-1), torch.ones(R))
    for value in (out["tokens"], out["rgb"], out["weights"]):
        assert torch.isfinite(value).all()


def test_masking_value_is_finite_for_half_precision():
    for dtype in (torch.float16, torch.bfloat16, torch.float32):
        value = masking_value(dtype)
        logits = torch.full((3,), value, dtype=dtype)
        assert math.isfinite(float(torch.tensor(value, dtype=dtype)))
        torch.testing.assert_close(torch.softmax(logits.float(), 0), torch.full((3,), 1 / 3))


def test_eval_is_deterministic_and_training_dropout_is_seeded():
    field, ray = build(dropout=0.1)
    inputs = make_inputs()
    first = run(field.eval(), ray.eval(), inputs)
    second = run(field, ray, inputs)
    torch.testing.assert_close(first["rgb"], second["rgb"], rtol=0, atol=0)
    field.train(), ray.train()
    torch.manual_seed(5)
    a = run(field, ray, inputs)
    torch.manual_seed(5)
    b = run(field, ray, inputs)
    torch.manual_seed(6)
    c = run(field, ray, inputs)
    torch.testing.assert_close(a["rgb"], b["rgb"], rtol=0, atol=0)
    assert not torch.allclose(a["rgb"], c["rgb"])
    assert not torch.allclose(a["rgb"], first["rgb"])
    # Readout weights are renormalised after dropout; the returned attention is the dropped-out one.
    torch.testing.assert_close(a["weights"].sum(dim=-1), torch.ones(R))
    assert (a["view_attention"][0] == 0).any() and (a["ray_attention"][0] == 0).any()


def test_zero_dropout_never_calls_dropout(monkeypatch):
    def forbidden(*args, **kwargs):
        raise AssertionError("dropout called with p = 0")

    monkeypatch.setattr(common, "dropout_mask", forbidden)
    field, ray = build(dropout=0.0)
    run(field.train(), ray.train(), make_inputs())
    with pytest.raises(AssertionError, match="dropout called"):
        field2, ray2 = build(dropout=0.1)
        run(field2.train(), ray2.train(), make_inputs())


@pytest.mark.parametrize("p", [0.1, 0.5, 0.9])
def test_the_dropout_mask_is_dropout_forward_and_backward(p):
    """Against the straightforward computation: x * (mask / (1 - p')) with the same mask, its gradient the mask; the
    dropped fraction is p' = round(p * 65536) / 65536 within sampling error; seeded like F.dropout."""
    x = torch.randn(64, 33, 17, requires_grad=True)
    torch.manual_seed(3)
    y = common.maybe_dropout(x, p, training=True)
    torch.manual_seed(3)
    mask = common.dropout_mask(x.detach(), p)
    kept = mask != 0
    scale = common.LEVELS / (common.LEVELS - round(p * common.LEVELS))
    assert torch.equal(mask[kept], torch.full_like(mask[kept], scale))
    torch.testing.assert_close(y, torch.where(kept, x * scale, torch.zeros_like(x)), rtol=0, atol=0)
    y.backward(torch.ones_like(y))
    torch.testing.assert_close(x.grad, mask, rtol=0, atol=0)
    dropped = 1 - kept.float().mean().item()
    assert abs(dropped - p) < 4 * (p * (1 - p) / kept.numel()) ** 0.5
    big = torch.ones(1 << 20)
    assert abs(common.maybe_dropout(big, p, training=True).mean().item() - 1.0) < 0.01  # unbiased
    assert common.maybe_dropout(x, p, training=False) is x


def test_gradients_reach_every_parameter():
    field, ray = build(dropout=0.1)
    field.train(), ray.train()
    out = run(field, ray, make_inputs())
    sem = torch.randn(R, S, V, D)  # a stand-in semantic field that reuses the attention, as the pipeline does
    loss = out["rgb"].square().sum()
    for a, r in zip(out["view_attention"], out["ray_attention"]):
        loss = loss + (a * sem).sum() + (r * torch.randn_like(r)).sum()
    loss.backward()
    for name, p in [*field.named_parameters(), *ray.named_parameters()]:
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        if name.endswith("attn.attn_fc.2.bias"):
            # Constant over views per channel, so the softmax over views cancels it (as in GNT).
            assert p.grad.abs().max() < 1e-4, name
        else:
            assert p.grad.abs().max() > 0, name


def test_view_permutation_invariance():
    field, ray = build(dropout=0.0)
    field.eval(), ray.eval()
    features, samples, rays = make_inputs()
    perm = torch.tensor([2, 0, 1])
    permuted = ProjectedFeatures(
        rgb_features=features.rgb_features[:, :, perm],
        semantic=None,
        ray_diff=features.ray_diff[:, :, perm],
        visible=features.visible[:, :, perm],
    )
    a = run(field, ray, (features, samples, rays))
    b = run(field, ray, (permuted, samples, rays))
    for key in ("tokens", "rgb", "weights"):
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6)
    for x, y in zip(a["view_attention"], b["view_attention"]):
        torch.testing.assert_close(x[:, :, perm], y, rtol=1e-5, atol=1e-6)


def test_positional_encoding_order():
    x = torch.randn(4, 3)
    enc = positional_encoding(x, 3)
    assert enc.shape == (4, 21)
    torch.testing.assert_close(enc[:, :3], x)
    torch.testing.assert_close(enc[:, 3:6], torch.sin(x))
    torch.testing.assert_close(enc[:, 6:9], torch.cos(x))
    torch.testing.assert_close(enc[:, 15:18], torch.sin(4 * x))
    assert positional_encoding(x, 0) is x


def test_config_errors():
    with pytest.raises(ConfigError, match="num_heads=3"):
        GNTRayTransformer(in_dim=16, num_blocks=2, num_heads=3)
    with pytest.raises(ConfigError, match="dropout"):
        GNTRayTransformer(in_dim=16, num_blocks=2, dropout=1.0)
    with pytest.raises(ConfigError, match="attn_hidden_ratio"):
        GNTViewTransformer(in_dim=11, width=4, attn_hidden_ratio=8)
    with pytest.raises(ConfigError, match="num_blocks"):
        GNTViewTransformer(in_dim=11, width=16, num_blocks=0)


def test_wrong_input_width_is_a_data_error():
    field, _ = build()
    features, samples, rays = make_inputs()
    bad = ProjectedFeatures(features.rgb_features[..., :-1], None, features.ray_diff, features.visible)
    with pytest.raises(DataError, match="in_dim=11"):
        field.begin(bad, samples, rays)


def test_registered_and_built_from_config():
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.transformers.plugin",), autoload=False))
    assert not registry.problems
    field = registry.build("field_aggregator", {"name": "gnt_view", "width": 16, "num_blocks": 2}, in_dim=IN_DIM)
    ray = registry.build("ray_aggregator", {"name": "gnt_ray", "num_heads": 2}, in_dim=field.width,
                         num_blocks=field.num_blocks)
    assert isinstance(field, GNTViewTransformer) and isinstance(ray, GNTRayTransformer)
    assert (field.width, field.num_blocks, ray.num_heads, ray.num_blocks) == (16, 2, 2, 2)
    with pytest.raises(ConfigError, match="num_heads"):
        registry.build("field_aggregator", {"name": "gnt_view", "num_heads": 4}, in_dim=IN_DIM)


@pytest.mark.parametrize("samples", [3, 8, 15, 16, 48])
def test_softmax_over_a_rays_samples_is_torchs_without_autograd_to_an_ulp_and_exactly_with_it(samples):
    scores = torch.randn(64, 4, samples, samples, generator=torch.Generator().manual_seed(samples)) * 4
    expected = torch.softmax(scores, dim=-1)
    with torch.no_grad():
        fast = common.softmax_last(scores)
    assert (fast - expected).abs().max().item() <= 3e-7 and torch.allclose(fast.sum(-1), torch.ones(64, 4, samples))
    if samples >= common.SHORT_SOFTMAX:
        assert torch.equal(fast, expected)  # long rows: torch's kernel is the faster one and is used
    trained = scores.clone().requires_grad_(True)
    assert torch.equal(common.softmax_last(trained), expected)  # a training step keeps torch's numerics
    with torch.no_grad():  # rows of one very large score: no overflow, no NaN
        peaked = common.softmax_last(torch.full((2, samples), -1e9).index_fill_(1, torch.tensor([0]), 1e9))
    assert torch.equal(peaked[:, 0], torch.ones(2))
