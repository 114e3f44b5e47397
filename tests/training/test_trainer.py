"""Training loop: one forward shared with evaluation, batches of target views, NaN stops, exact resume, lr groups."""

from pathlib import Path

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError, DataError, NonFiniteError
from gpnerf_core.interfaces import LossSet
from gpnerf_core.model.checkpoint import read_checkpoint
from gpnerf_core.training.trainer import loss_inputs
from gpnerf_core.types import StepBatch
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer


def tiny_cfg(tmp_path, *extra):
    return compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}", *extra])


class PoisonedLoss(LossSet):
    """Returns a NaN term on its second call."""

    needs_semantics = False

    def __init__(self):
        super().__init__()
        self.calls = 0

    def forward(self, inputs):
        self.calls += 1
        value = (inputs.coarse.rgb - inputs.target_rgb).pow(2).mean()
        return {"rgb": value, "sd": value * (float("nan") if self.calls == 2 else 0.0)}


def test_nan_loss_stops_training_naming_step_term_and_view(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.steps=3")
    components = build_components(cfg)
    components.loss = PoisonedLoss()
    trainer = make_trainer(cfg, tmp_path / "run", components=components)
    with pytest.raises(NonFiniteError, match=r"step 1: loss term 'sd' is nan \(scene 'layout_00' frame \d+\)"):
        trainer.fit(progress=False)
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_learning_rate_groups(tmp_path):
    cfg = tiny_cfg(tmp_path, "model.lr.feature_extractor=0.1", "model.lr.transformer=0.2", "model.lr.head=0.3")
    trainer = make_trainer(cfg, tmp_path / "run")
    rates = {group["name"]: group["lr"] for group in trainer.optimizer.param_groups}
    assert rates == {"feature_extractor": 0.1, "transformer": 0.2, "head": 0.3}
    extractor_params = {id(p) for p in trainer.model.extractor.parameters()}
    assert {id(p) for p in trainer.optimizer.param_groups[0]["params"]} == extractor_params


def test_forward_gives_every_output_the_losses_read(tmp_path):
    cfg = tiny_cfg(tmp_path)
    trainer = make_trainer(cfg, tmp_path / "run")
    batch = trainer.sampler.next_batch()
    view = batch.views[0]
    output = trainer.model(batch, semantics=True, sample_semantics=True).views[0]
    rays, (height, width) = view.num_rays, view.camera.image_size
    assert output.coarse.rgb.shape == (rays, 3) and output.fine.rgb.shape == (rays, 3)
    assert output.fine.sample_semantic.shape[:2] == (rays, 8)  # 6 coarse + 2 fine samples
    channels = output.teacher_map.shape[1]
    assert output.teacher_at_rays.shape == (rays, channels)
    assert output.logits.shape[-2:] == (height, width)
    # The fused map is the teacher map except in the cells the rays hit, which hold rendered features.
    changed = (output.head_input != output.teacher_map).any(dim=1).flatten()
    cells = (view.pixels[:, 1].long() // 2) * (width // 2) + view.pixels[:, 0].long() // 2
    hit = torch.zeros_like(changed)
    hit[cells] = True
    assert not changed[~hit].any() and changed[hit].all()
    inputs = loss_inputs(view, output, ignore_index=255)
    row, col = int(view.pixels[0, 1]), int(view.pixels[0, 0])
    assert torch.equal(inputs.target_rgb[0], view.image[:, row, col])


def test_rendering_noise_follows_the_view_seed_not_the_process(tmp_path):
    cfg = tiny_cfg(tmp_path)
    trainer = make_trainer(cfg, tmp_path / "run")
    batch = trainer.sampler.next_batch()
    first = trainer.model(batch, semantics=False).views[0].coarse.samples.depths
    torch.manual_seed(1234)  # the global RNG plays no part
    again = trainer.model(batch, semantics=False).views[0].coarse.samples.depths
    assert torch.equal(first, again)
    trainer.model.eval()
    deterministic = trainer.model(batch, semantics=False).views[0].coarse.samples.depths
    assert not torch.equal(first, deterministic)


def test_two_targets_per_step_is_the_mean_of_each_target_alone(tmp_path):
    """The loss of a 2-view step is the mean of the two views' losses (what DDP's gradient average needs)."""
    cfg = tiny_cfg(tmp_path, "train.targets_per_step=2")
    trainer = make_trainer(cfg, tmp_path / "run")
    batch = trainer.sampler.next_batch()
    assert len(batch.views) == 2
    both = trainer._loss_terms(batch, trainer.model(batch, semantics=True, sample_semantics=True))
    singles = [
        trainer._loss_terms(StepBatch((v,)), trainer.model(StepBatch((v,)), semantics=True, sample_semantics=True))
        for v in batch.views
    ]
    for name, value in both.items():
        torch.testing.assert_close(value, (singles[0][name] + singles[1][name]) / 2)


def test_global_batch_is_split_across_processes_the_same_way_at_any_world_size(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.targets_per_step=4")
    one = make_trainer(cfg, tmp_path / "a").sampler
    from gpnerf_core.training.sampler import StepSampler

    def sampler(rank, world):
        return StepSampler(one.frames, one.selector, scene_names=one.scene_names, num_source_views=2,
                           rays_per_view=16, targets_per_step=4, seed=0, rank=rank, world_size=world)

    whole = [(v.scene, v.frame, v.render_seed) for v in sampler(0, 1).next_batch().views]
    halves = [(v.scene, v.frame, v.render_seed) for r in (0, 1) for v in sampler(r, 2).next_batch().views]
    assert whole == halves
    with pytest.raises(ConfigError, match="targets_per_step=4 is not divisible by the world size 3"):
        sampler(0, 3)


def test_resume_continues_exactly(tmp_path):
    torch.manual_seed(0)
    cfg = tiny_cfg(tmp_path, "train.steps=4", "train.checkpoint_every=2")
    straight = make_trainer(cfg, tmp_path / "a")
    straight_result = straight.fit(progress=False)

    torch.manual_seed(0)
    first = make_trainer(tiny_cfg(tmp_path, "train.steps=2"), tmp_path / "b")
    first.fit(progress=False)
    checkpoint = Path(tmp_path / "b" / "checkpoints" / "step_0000002.pt")

    torch.manual_seed(123)  # resuming must not depend on the state the process happens to be in
    resumed = make_trainer(tiny_cfg(tmp_path, "train.steps=4", f"train.resume={checkpoint}"), tmp_path / "c")
    resumed_result = resumed.fit(progress=False)
    assert [h["loss"] for h in resumed_result.history] == [h["loss"] for h in straight_result.history]
    for (name, a), (_, b) in zip(straight.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name


def test_checkpoint_explains_itself(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.steps=1")
    trainer = make_trainer(cfg, tmp_path / "run")
    path = trainer.fit(progress=False).checkpoint
    state = read_checkpoint(path)
    assert state["format"] == 2 and state["step"] == 1
    assert "feature_extractor" in state["config"] and len(state["config_sha256"]) == 64
    assert {"gpnerf_core", "torch"} <= set(state["versions"])
    # Loadable without unpickling code.
    torch.load(path, weights_only=True)


def test_resume_with_another_model_config_is_refused_naming_the_keys(tmp_path):
    trainer = make_trainer(tiny_cfg(tmp_path, "train.steps=1"), tmp_path / "run")
    checkpoint = trainer.fit(progress=False).checkpoint
    other = tiny_cfg(tmp_path, "train.steps=2", f"train.resume={checkpoint}", "loss.sd_weight=0.5")
    with pytest.raises(ConfigError, match=r"loss.sd_weight: 0.25 -> 0.5.*train.resume_strict=false"):
        make_trainer(other, tmp_path / "run2")
    relaxed = tiny_cfg(tmp_path, "train.steps=2", f"train.resume={checkpoint}", "loss.sd_weight=0.5",
                       "train.resume_strict=false")
    trainer = make_trainer(relaxed, tmp_path / "run2")
    assert trainer.step == 1 and any("loss.sd_weight" in note for note in trainer.notes)


def test_checkpoint_of_another_model_size_names_the_first_tensor(tmp_path):
    trainer = make_trainer(tiny_cfg(tmp_path, "train.steps=1"), tmp_path / "run")
    checkpoint = trainer.fit(progress=False).checkpoint
    wider = tiny_cfg(tmp_path, f"train.resume={checkpoint}", "model.feature_extractor.widths=[8,8,8,24]", "train.resume_strict=false")
    with pytest.raises(DataError) as error:
        make_trainer(wider, tmp_path / "run2")
    message = str(error.value)
    assert "\n" not in message and "has shape [" in message and "expects [" in message and "extractor." in message


def test_truncated_checkpoint_is_one_line(tmp_path):
    trainer = make_trainer(tiny_cfg(tmp_path, "train.steps=1"), tmp_path / "run")
    checkpoint = trainer.fit(progress=False).checkpoint
    cut = tmp_path / "cut.pt"
    cut.write_bytes(checkpoint.read_bytes()[:2000])
    with pytest.raises(DataError) as error:
        read_checkpoint(cut)
    assert str(error.value).startswith(f"checkpoint {cut} could not be read") and "\n" not in str(error.value)


def test_activation_checkpointing_gives_the_same_loss_and_gradients(tmp_path):
    results = []
    for flag in ("false", "true"):
        torch.manual_seed(0)
        trainer = make_trainer(tiny_cfg(tmp_path, f"model.checkpoint_blocks={flag}"), tmp_path / flag)
        batch = trainer.sampler.next_batch()
        terms = trainer._loss_terms(batch, trainer.model(batch, semantics=True, sample_semantics=True))
        sum(terms.values()).backward()
        results.append((terms, {n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None}))
    (terms_a, grads_a), (terms_b, grads_b) = results
    for name in terms_a:
        torch.testing.assert_close(terms_a[name], terms_b[name], rtol=0, atol=0)
    assert grads_a.keys() == grads_b.keys()
    for name in grads_a:
        torch.testing.assert_close(grads_a[name], grads_b[name], rtol=1e-5, atol=1e-7, msg=name)


def _loss_and_gradients(trainer):
    batch = trainer.sampler.next_batch()
    terms = trainer._loss_terms(batch, trainer.model(batch, semantics=True, sample_semantics=True))
    sum(terms.values()).backward()
    return terms, {n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None}


def test_channels_last_source_maps_give_bitwise_the_same_step_and_rendering(tmp_path):
    """The layout only changes how ``grid_sample`` reads the maps: float32 loss, gradients and a rendered view are
    identical. The maps are copied channels-last only where each is sampled at more points than it has pixels (the
    tiny maps: 16 x 24 = 384; a step of 48 rays x 8 samples reaches it, one of 16 rays does not; a whole view does)."""
    from gpnerf_core.geometry.projection import Projector

    seen = []
    original = Projector.__call__

    def recording(self, samples, origins, sources, features, *, with_semantic):
        if with_semantic:
            seen.append(features.semantic.is_contiguous(memory_format=torch.channels_last))
        return original(self, samples, origins, sources, features, with_semantic=with_semantic)

    results, renders, layouts = {}, {}, {}
    Projector.__call__ = recording
    try:
        for flag, rays in (("false", 48), ("true", 48)):
            torch.manual_seed(0)
            cfg = tiny_cfg(tmp_path, f"model.channels_last_maps={flag}", f"train.rays={rays}")
            trainer = make_trainer(cfg, tmp_path / f"{flag}_{rays}")
            seen.clear()
            results[flag, rays] = _loss_and_gradients(trainer)
            training = set(seen)
            seen.clear()
            view = trainer.sampler.next_batch().views[0]
            trainer.model.eval()
            with torch.inference_mode():
                renders[flag, rays] = trainer.model.predict(view.camera, view.sources, stride=0, chunk_rays=50)
            layouts[flag, rays] = (training, set(seen))
    finally:
        Projector.__call__ = original
    assert layouts == {("false", 48): ({False}, {False}), ("true", 48): ({True}, {True})}
    maps = torch.zeros(2, 4, 16, 24)  # 384 pixels; the tiny model draws 6 + 2 samples per ray
    copied = [trainer.model._for_sampling(maps, rays).is_contiguous(memory_format=torch.channels_last)
              for rays in (47, 48)]
    assert copied == [False, True]
    (terms_a, grads_a), (terms_b, grads_b) = results["false", 48], results["true", 48]
    assert terms_a.keys() == terms_b.keys() and grads_a.keys() == grads_b.keys()
    for name in terms_a:
        assert torch.equal(terms_a[name], terms_b[name]), name
    for name in grads_a:
        assert torch.equal(grads_a[name], grads_b[name]), name
    for field in ("rgb", "depth", "semantic", "logits"):
        assert torch.equal(getattr(renders["false", 48], field), getattr(renders["true", 48], field)), field


def test_compiled_blocks_give_the_eager_loss_and_gradients(tmp_path):
    """``model.compile``: the traced block pairs and attention sums compute the eager step. ``aot_eager`` traces
    through dynamo and AOT autograd like inductor but skips code generation (inductor's C++ build takes a minute
    here); inductor itself is measured by ``bench`` (docs/benchmarks.md)."""
    import torch._dynamo

    results = []
    for overrides in (("model.compile=false",), ("model.compile=true", "model.compile_backend=aot_eager")):
        torch.manual_seed(0)
        torch._dynamo.reset()
        trainer = make_trainer(tiny_cfg(tmp_path, *overrides), tmp_path / overrides[0])
        results.append(_loss_and_gradients(trainer))
    torch._dynamo.reset()
    (terms_a, grads_a), (terms_b, grads_b) = results
    assert terms_a.keys() == terms_b.keys() and grads_a.keys() == grads_b.keys()
    for name in terms_a:
        torch.testing.assert_close(terms_a[name], terms_b[name], rtol=1e-5, atol=1e-6, msg=name)
    for name in grads_a:
        torch.testing.assert_close(grads_a[name], grads_b[name], rtol=1e-4, atol=1e-6, msg=name)


def test_an_unknown_compile_backend_is_one_line_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"model\.compile_backend='nonsense'.*known"):
        make_trainer(tiny_cfg(tmp_path, "model.compile=true", "model.compile_backend=nonsense"), tmp_path / "bad")


def _straightforward_terms(trainer, view):
    """The step computed the plain way: one extractor pass over sources and target together, nothing skipped."""
    from gpnerf_core.model.context_decoding import cells_of_pixels, fuse_rendered, gather_cells
    from gpnerf_core.geometry import rays_through_pixels
    from gpnerf_core.types import FeatureMaps, ViewOutput

    model, sources, camera = trainer.model, view.sources, view.camera
    maps = model.encode(torch.cat([sources.rgb, view.image[None]]))
    count = sources.num_views
    source_maps = FeatureMaps(radiance=maps.radiance[:count], semantic=maps.semantic[:count])
    rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
    generator = torch.Generator().manual_seed(view.render_seed)
    coarse, fine = model.render_rays(rays, sources, source_maps, randomized=True, with_semantic=True,
                                     with_sample_semantic=trainer.loss.needs_sample_semantics, generator=generator)
    teacher = maps.semantic[count:]
    cells = cells_of_pixels(view.pixels, camera.image_size, tuple(teacher.shape[-2:]))
    head_input = fuse_rendered(teacher, fine.semantic, cells)
    output = ViewOutput(coarse, fine, teacher, gather_cells(teacher, cells), head_input,
                        model.decode(head_input, camera.image_size).logits)
    return trainer.loss(loss_inputs(view, output, trainer.ignore_index))


def test_the_forward_equals_the_straightforward_computation_with_its_gradients(tmp_path):
    """forward encodes the target apart and drops the sources' FPN graph early; loss and gradients are unchanged.

    The loss set is ``sd`` (smooth in every input): the D.G window's argmax would turn the 1e-5 differences of two
    convolution batchings into different windows, and so into different gradients.
    """
    cfg = compose(["+head=unet", "+loss=sd", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"])
    trainer = make_trainer(cfg, tmp_path / "run")
    trainer.model.double()  # float64, so the two convolution batchings agree far below the tolerance
    batch = StepBatch(tuple(_in_float64(view) for view in trainer.sampler.next_batch().views))
    results = []
    needs_samples = trainer.loss.needs_sample_semantics
    view = batch.views[0]

    def through_forward():
        output = trainer.model(batch, semantics=True, sample_semantics=needs_samples).views[0]
        return trainer.loss(loss_inputs(view, output, trainer.ignore_index))

    for compute in (through_forward, lambda: _straightforward_terms(trainer, view)):
        trainer.model.zero_grad(set_to_none=True)
        terms = compute()
        sum(terms.values()).backward()
        grads = {n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None}
        results.append(({k: v.detach() for k, v in terms.items()}, grads))
    (terms, grads), (reference_terms, reference_grads) = results
    for name in reference_terms:
        torch.testing.assert_close(terms[name], reference_terms[name], rtol=1e-10, atol=1e-12)
    assert grads.keys() == reference_grads.keys()
    for name, reference in reference_grads.items():
        torch.testing.assert_close(grads[name], reference, rtol=1e-7, atol=1e-9, msg=lambda m: f"{name}: {m}")


def _in_float64(view):
    import dataclasses

    camera = dataclasses.replace(view.camera, intrinsics=view.camera.intrinsics.double(), c2w=view.camera.c2w.double())
    sources = dataclasses.replace(view.sources, rgb=view.sources.rgb.double(),
                                  intrinsics=view.sources.intrinsics.double(), c2w=view.sources.c2w.double())
    return dataclasses.replace(view, camera=camera, sources=sources, image=view.image.double(),
                               depth=view.depth.double(), pixels=view.pixels.double())


def _poison(phase, at_step, change):
    """A command callback at ``phase`` that applies ``change(model)`` once, at step ``at_step``."""
    from gpnerf_core.interfaces.training import TrainingCallback

    def run(state):
        if state.step == at_step:
            change()
    return TrainingCallback(phase, run)


def test_a_checkpoint_holding_nan_is_not_written_so_auto_resume_takes_the_last_finite(tmp_path):
    from gpnerf_core.interfaces.training import TrainingPhase
    from gpnerf_core.training.resume import newest_intact_checkpoint

    cfg = tiny_cfg(tmp_path, "train.steps=4", "train.checkpoint_every=2")
    trainer = make_trainer(cfg, tmp_path / "run")
    name, parameter = next(iter(trainer.model.named_parameters()))

    def turn_nan():
        with torch.no_grad():
            parameter.view(-1)[0] = float("nan")

    with pytest.raises(NonFiniteError) as error:
        trainer.fit(progress=False, callbacks=[_poison(TrainingPhase.AFTER_STEP, 3, turn_nan)])
    message = str(error.value)
    assert "\n" not in message and f"parameter {name!r} holds NaN or Inf" in message
    assert message.startswith("step 4: checkpoint step_0000004.pt: model 'gnt'") and "not written" in message
    assert [p.name for p in (tmp_path / "run" / "checkpoints").iterdir()] == ["step_0000002.pt"]
    assert newest_intact_checkpoint(tmp_path / "run")[0].name == "step_0000002.pt"


def test_a_parameter_that_changes_shape_without_changes_size_is_refused_naming_ema_decay(tmp_path):
    from gpnerf_core.errors import PluginError
    from gpnerf_core.interfaces.training import TrainingPhase

    trainer = make_trainer(tiny_cfg(tmp_path, "train.steps=2", "train.ema_decay=0.9"), tmp_path / "run")
    owner, key = next((m, k) for m in trainer.model.modules() for k, p in m.named_parameters(recurse=False)
                      if p.dim() == 1)

    def grow():
        old = getattr(owner, key)
        setattr(owner, key, torch.nn.Parameter(torch.cat([old.detach(), old.detach()[:1]])))

    with pytest.raises(PluginError) as error:
        trainer.fit(progress=False, callbacks=[_poison(TrainingPhase.AFTER_BACKWARD, 0, grow)])
    message = str(error.value)
    assert "\n" not in message and "capabilities.changes_size is False" in message
    assert "train.ema_decay=0.9" in message and "step 0, after its after_backward callbacks" in message


def test_resume_refuses_optimizer_state_that_does_not_fit_the_parameters_in_one_line(tmp_path):
    from gpnerf_core.model.trained import load_trained

    checkpoint = make_trainer(tiny_cfg(tmp_path, "train.steps=1"), tmp_path / "run").fit(progress=False).checkpoint
    read = load_trained(checkpoint)
    moments = read.state["optimizer"]["state"][0]
    moments["exp_avg"] = moments["exp_avg"].flatten()[:-1].clone()  # tampered: not the parameter's shape
    cfg = tiny_cfg(tmp_path, "train.steps=2", f"train.resume={checkpoint}")
    with pytest.raises(ConfigError) as error:
        make_trainer(cfg, tmp_path / "run2", resume_from=read)
    message = str(error.value)
    assert "\n" not in message and "its optimizer state does not fit the parameters" in message
    assert "exp_avg of parameter" in message
