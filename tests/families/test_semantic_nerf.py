"""Semantic-NeRF (``model=semantic_nerf``, per scene): NeRF's encodings and skip, the density with the ray's length
and the far interval, label rendering of both passes, jitter and density noise only in training, the per-scene
refusals, and a tiny run (train, score the held-out frames, render one frame) through the unchanged commands."""

from __future__ import annotations

import json

import pytest
import torch

from gpnerf_core.cli import main as cli_main
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry import compositing_weights, rays_through_pixels
from gpnerf_core.model.build import build_components
from gpnerf_plugins.families.nerf_field import NeRFField, positional_encoding
from gpnerf_plugins.families.semantic_nerf.model import SemanticNeRF
from pipeline_check import TINY_CLI, for_parts, TINY_SCENES, in_process

SMALL = dict(num_classes=5, coarse_samples=8, fine_samples=4, width=16, depth=4, skip=1, position_scale=0.1,
             position_frequencies=3, direction_frequencies=2, density_noise=1.0, inverse_depth=False)
TINY = ["model.width=16", "model.depth=3", "model.skip=1", "model.coarse_samples=4", "model.fine_samples=4",
        "train.rays=16", "eval.chunk_rays=512"]


def _rays(count: int = 6):
    pixels = torch.rand(count, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor([47.0, 31.0])
    intrinsics = torch.tensor([[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])
    return rays_through_pixels(pixels, intrinsics, torch.eye(4), 0.2, 6.0)


def test_the_encodings_are_nerfs():
    x = torch.tensor([[0.1, -0.2, 0.3]])
    expected = torch.cat([x, torch.sin(x), torch.cos(x), torch.sin(2 * x), torch.cos(2 * x)], -1)
    assert torch.allclose(positional_encoding(x, 2), expected)
    assert positional_encoding(x, 10).shape[-1] == 63 and positional_encoding(x, 4).shape[-1] == 27
    field = NeRFField(width=16, depth=5, skip=2, position_frequencies=10, direction_dim=27)
    assert [layer.in_features for layer in field.trunk] == [63, 16, 16, 16 + 63, 16]  # joins after layer 2


def test_the_density_counts_the_ray_length_and_the_last_interval_absorbs_the_rest():
    model = SemanticNeRF(**SMALL).eval()
    for field in (model.coarse, model.fine):
        field.density.bias.data.fill_(1.0)  # densities above 0 (untrained, most are clipped to 0 by the ReLU)
    rays = _rays()
    with torch.no_grad():
        coarse, fine = model.render_rays(rays, True, None)
    assert coarse.samples.depths.shape == (6, 8) and fine.samples.depths.shape == (6, 12)
    for rendered in (coarse, fine):  # the far interval (1e10) takes what is left: every ray's weights sum to 1
        assert torch.allclose(rendered.weights.sum(-1), torch.ones(6), atol=1e-5)
        assert torch.allclose(rendered.depth, (rendered.weights * rendered.samples.depths).sum(-1))
        assert rendered.logits.shape == (6, 5)
    # the same pass by hand: ReLU(raw density) x interval x |d|, on the same encoded inputs
    samples, norms = coarse.samples, rays.directions.norm(dim=-1)
    position = samples.points.reshape(-1, 3) * 0.1  # the field encodes it (3 octaves)
    direction = positional_encoding(rays.directions / norms[:, None], 2).repeat_interleave(8, 0)
    with torch.no_grad():
        raw, colour, scores = model.coarse(position, direction, True)
    intervals = torch.cat([samples.depths[:, 1:] - samples.depths[:, :-1], torch.full((6, 1), 1e10)], -1)
    weights = compositing_weights(1 - torch.exp(-torch.relu(raw.view(6, 8)) * intervals * norms[:, None]))
    assert torch.allclose(coarse.weights, weights, atol=1e-6)
    assert torch.allclose(coarse.logits, torch.einsum("rs,rsk->rk", weights, scores.view(6, 8, 5)), atol=1e-5)


def test_samples_and_density_jitter_only_in_training_with_the_views_generator():
    model = SemanticNeRF(**SMALL)
    rays = _rays()
    with torch.no_grad():
        exact = model.render_rays(rays, True, None)[0]
        draws = [model.render_rays(rays, True, torch.Generator().manual_seed(4))[0] for _ in range(2)]
    assert torch.equal(draws[0].rgb, draws[1].rgb) and not torch.equal(draws[0].rgb, exact.rgb)
    assert not torch.equal(draws[0].samples.depths, exact.samples.depths)
    assert torch.allclose(exact.samples.depths[0], torch.linspace(0.2, 6.0, 8))  # uniform in depth, bin edges


def test_per_scene_refusals(tmp_path):
    common = ["+experiment=baselines/semantic_nerf", *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"]
    with pytest.raises(ConfigError, match=r"drop \+head=unet"):
        build_components(compose([*common, "+head=unet"]))
    with pytest.raises(ConfigError, match=r"^model.skip=3: expected in \[0, model.depth - 1\) = \[0, 3\)$"):
        build_components(compose([*common, "model.depth=4", "model.skip=3"]))
    assert build_components(compose(common)).model.capabilities.generalizable is False


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    out = tmp_path_factory.mktemp("semantic_nerf") / "run"
    argv = ["run", "+experiment=baselines/semantic_nerf", *for_parts(TINY_CLI), *TINY, "dataset.scenes=[layout_00]",
            "train.steps=2", f"out_dir={out}"]
    assert cli_main(argv) == 0
    return out


def test_run_fits_one_scene_and_scores_its_held_out_frames(fitted, capsys):
    metrics = json.loads((fitted / "metrics.json").read_text())
    assert set(metrics["eval"]) == {"train_heldout"}
    assert 0.0 <= metrics["eval"]["train_heldout"]["miou/image_mean_present"] <= 1.0
    assert json.loads((fitted / "plugins.json").read_text())["used"]["model"]["name"] == "semantic_nerf"
    several = in_process(*["run", "+experiment=baselines/semantic_nerf", *for_parts(TINY_CLI), *TINY, "dataset.num_train_scenes=2",
                        "train.steps=1", f"out_dir={fitted.parent / 'two'}"])
    unseen = in_process(*["run", "+experiment=baselines/semantic_nerf", *for_parts(TINY_CLI), *TINY, "dataset.scenes=[layout_00]",
                       "eval.splits=[train,unseen]", "train.steps=1", f"out_dir={fitted.parent / 'unseen'}"])
    err = capsys.readouterr().err
    assert several == 2 and "model=semantic_nerf is fitted per scene: expected one training scene" in err
    assert unseen == 2 and "asks for unseen scenes; expected eval.splits=[train]" in err
    assert not (fitted.parent / "two").exists() and not (fitted.parent / "unseen").exists()


def test_render_draws_a_frame_of_the_scene_from_its_own_field(fitted, tmp_path):
    checkpoint = next((fitted / "checkpoints").glob("*.pt"))
    assert cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"]) == 0
    written = json.loads((tmp_path / "video" / "render.json").read_text())
    assert written["frames"] == 1 and written["scene"] == "layout_00"  # its own scene, not the first unseen one


def test_a_per_scene_model_is_refused_any_scene_but_its_own(fitted, tmp_path, capsys):
    checkpoint = next((fitted / "checkpoints").glob("*.pt"))
    other = in_process("render", f"checkpoint={checkpoint}", "render.scene=unseen_00", "render.frames=1",
                       f"out_dir={tmp_path / 'video'}")
    scored = in_process("eval", f"checkpoint={checkpoint}", "dataset.scenes=[layout_01]", "dataset.num_train_scenes=2",
                        f"out_dir={tmp_path / 'eval'}")
    err = capsys.readouterr().err
    assert other == 2 and ("render.scene='unseen_00': model 'semantic_nerf' was fitted on scene 'layout_00' alone "
                           "(checkpoint") in err and "expected render.scene=layout_00 or render.scene left out" in err
    assert scored == 2 and ("eval: model 'semantic_nerf' was fitted on scene 'layout_00' alone" in err
                            and "asked for 'layout_01': dataset=embedded holds 'layout_01', not 'layout_00'" in err)
    assert not (tmp_path / "video").exists() and not (tmp_path / "eval").exists()


# ---- the grid option (model.field=grid) ------------------------------------------------------------------------------

GRID = dict(SMALL, field="grid", grid_levels=3, grid_features=2, grid_table_log2=6, grid_base_resolution=2.0,
            grid_finest_resolution=8.0, grid_width=16)


def _instant_ngp_encoding(encoding, positions):
    """Instant-NGP's encoding written out corner by corner: per level, the 8 cell corners hashed
    (x * 1 ^ y * 2654435761 ^ z * 805459861 mod T) and weighted trilinearly."""
    import itertools

    levels = []
    for level, resolution in enumerate(encoding.resolutions.tolist()):
        scaled = positions * resolution
        lower = torch.floor(scaled)
        fraction = scaled - lower
        total = 0
        for corner in itertools.product((0, 1), repeat=3):
            c = lower.long() + torch.tensor(corner)
            hashed = (c[:, 0] * 1) ^ (c[:, 1] * 2654435761) ^ (c[:, 2] * 805459861)
            rows = hashed % encoding.table_size + level * encoding.table_size
            weight = torch.ones(len(positions))
            for axis in range(3):
                weight = weight * (fraction[:, axis] if corner[axis] else 1 - fraction[:, axis])
            total = total + weight[:, None] * encoding.tables[rows]
        levels.append(total)
    return torch.cat(levels, -1)


def test_the_hash_encoding_is_instant_ngps_values_and_gradients():
    from gpnerf_plugins.families.hash_grid import HashGridEncoding

    torch.manual_seed(0)
    encoding = HashGridEncoding(levels=16, features=2, table_log2=6, base_resolution=16, finest_resolution=1024)
    assert encoding.resolutions[0] == 16 and encoding.resolutions[-1] == 1024  # floor(N_min b^l), both ends
    assert torch.all(encoding.resolutions[1:] > encoding.resolutions[:-1])
    with torch.no_grad():
        encoding.tables.normal_()  # Instant-NGP's +-1e-4 start would hide a wrong corner
    positions = torch.rand(50, 3) * 4 - 2  # negative coordinates too: the field has no bounds
    upstream = torch.randn(50, 32)
    (encoding(positions) * upstream).sum().backward()
    ours, our_grad = encoding(positions), encoding.tables.grad.clone()
    encoding.tables.grad = None
    reference = _instant_ngp_encoding(encoding, positions)
    (reference * upstream).sum().backward()
    assert torch.allclose(ours, reference, atol=1e-5)
    assert torch.allclose(our_grad, encoding.tables.grad, atol=1e-5)


def test_the_grid_field_keeps_the_families_outputs_and_trains_its_tables_at_their_own_rate():
    model = SemanticNeRF(**GRID).eval()
    for field in (model.coarse, model.fine):
        field.density.bias.data[0] = 1.0  # densities above 0, as in the MLP's test
    rays = _rays()
    with torch.no_grad():
        coarse, fine = model.render_rays(rays, True, None)
    for rendered in (coarse, fine):
        assert torch.allclose(rendered.weights.sum(-1), torch.ones(6), atol=1e-5)
        assert rendered.logits.shape == (6, 5) and rendered.rgb.shape == (6, 3)
    groups = model.parameter_groups()
    assert [t.shape for t in groups["grid"]] == [(3 * 64, 2)] * 2  # coarse and fine tables
    assert {id(p) for p in model.parameters()} == {id(p) for group in groups.values() for p in group}
    assert not {id(p) for p in groups["grid"]} & {id(p) for p in groups["field"]}


def test_the_grid_variant_passes_the_contract_kit():
    from gpnerf_core.registry.plugins import BUILTIN_PLUGINS
    from gpnerf_core.testing import plugin_checks

    small = {key: value for key, value in GRID.items() if key != "num_classes"}
    checks = [check for check in plugin_checks(BUILTIN_PLUGINS, configs={"model/semantic_nerf": small})
              if check.component == "model/semantic_nerf"]
    assert checks
    for check in checks:
        check.run()


def test_grid_options_out_of_range_are_named(tmp_path):
    common = ["+experiment=baselines/semantic_nerf_grid", *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"]
    with pytest.raises(ConfigError, match=r"^model.field=voxels: expected one of mlp, grid$"):
        build_components(compose([*common, "model.field=voxels"]))
    with pytest.raises(ConfigError, match=r"model.grid_table_log2=30: expected in \[4, 24\].*"
                                          r"model.grid_finest_resolution=8.0: expected >= model.grid_base_resolution"):
        build_components(compose([*common, "model.grid_table_log2=30", "model.grid_finest_resolution=8"]))


def test_the_grid_variant_fits_one_scene_renders_it_and_repeats_itself(tmp_path):
    def fit(out):
        argv = ["run", "+experiment=baselines/semantic_nerf_grid", *for_parts(TINY_CLI), *TINY, "model.grid_table_log2=10",
                "model.grid_levels=4", "dataset.scenes=[layout_00]", "train.steps=2", f"out_dir={out}"]
        assert cli_main(argv) == 0
        return json.loads((out / "metrics.json").read_text())

    metrics, again = fit(tmp_path / "grid"), fit(tmp_path / "again")
    assert 0.0 <= metrics["eval"]["train_heldout"]["miou/image_mean_present"] <= 1.0
    assert metrics["train"]["final_loss"] == again["train"]["final_loss"]  # the same seed, the same numbers
    scores = [{k: v for k, v in m["eval"]["train_heldout"].items() if k != "timing"} for m in (metrics, again)]
    assert scores[0] == scores[1]
    checkpoint = next((tmp_path / "grid" / "checkpoints").glob("*.pt"))
    assert cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"]) == 0
    assert json.loads((tmp_path / "video" / "render.json").read_text())["frames"] == 1


@pytest.mark.parametrize("key, value, expected", [
    ("density_noise", float("inf"), "model.density_noise=inf: expected a finite number"),
    ("position_scale", float("inf"), "model.position_scale=inf: expected a finite number"),
    ("position_frequencies", 200, "model.position_frequencies=200: expected in [0, 30]"),
    ("grid_base_resolution", float("inf"), "model.grid_base_resolution=inf: expected a finite number"),
])
def test_an_infinite_or_overflowing_field_option_is_refused_naming_its_key(key, value, expected):
    options = {**SMALL, key: value, **({"field": "grid"} if key.startswith("grid_") else {})}
    with pytest.raises(ConfigError) as error:
        SemanticNeRF(**options)
    assert str(error.value) == expected
