"""The contract's image-space side: a family that trains on whole images returns images (``ImageOutput``, never pixels
as rays) and its loss set reads images (``ImageLossInputs``); it names its own learning-rate groups, sees the step
and its outputs through its hooks' callbacks, adds its own loss terms (weighted, logged, checked), and has every
trainable parameter in exactly one group."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf, open_dict
from torch import nn

from gpnerf_core import (
    Capabilities,
    ConfigError,
    FamilyHooks,
    ImageLossInputs,
    ImageOutput,
    LossSet,
    ModelFamily,
    NonFiniteError,
    Prediction,
    StepOutput,
    TrainingBatch,
    TrainingCallback,
    TrainingPhase,
)
from gpnerf_core.config.compose import compose
from gpnerf_core.model.build import build_components
from pipeline_check import TINY_SCENES, make_trainer


class FlatImageHooks(FamilyHooks):
    """Records the steps its callbacks see, whether the gradients exist before the optimizer step, the outputs the
    after-backward callback is handed, and gives one loss term of its own (``brightness``: the colour's mean)."""

    def callbacks(self):
        family = self.family

        def before(state):
            family.seen.append(("before", state.step))

        def after_backward(state):
            family.gradient_before_step.append(family.colour.grad is not None)
            family.handed.append(state.outputs)

        def after(state):
            family.seen.append(("after", state.step))

        return (TrainingCallback(TrainingPhase.BEFORE_STEP, before),
                TrainingCallback(TrainingPhase.AFTER_BACKWARD, after_backward),
                TrainingCallback(TrainingPhase.AFTER_STEP, after, every=2))

    def loss_terms(self, state, wanted):
        value = torch.sigmoid(self.family.colour).mean() * self.family.term_scale
        return {"brightness": value}


class FlatImage(ModelFamily):
    """One learned colour everywhere, at a learned depth: the smallest family that renders whole images."""

    capabilities = Capabilities(generalizable=False, accepts_head=False, trains_on=TrainingBatch.IMAGES,
                                source_encoding=None, loss_terms=("brightness",), hooks=FlatImageHooks)

    def __init__(self, *, stray: bool = False) -> None:
        super().__init__()
        self.colour = nn.Parameter(torch.zeros(3))
        self.distance = nn.Parameter(torch.ones(1))
        self.stray = nn.Parameter(torch.zeros(1)) if stray else None
        self.seen: list[tuple[str, int]] = []
        self.gradient_before_step: list[bool] = []
        self.handed = []
        self.views = []
        self.term_scale = 1.0

    @property
    def semantic_output(self):
        return None

    def parameter_groups(self):
        return {"colour": [self.colour], "field": [self.distance]}

    def forward(self, batch, *, semantics, sample_semantics=False):
        views = []
        for view in batch.views:
            self.views.append(view)
            h, w = view.camera.image_size
            views.append(ImageOutput(rgb=torch.sigmoid(self.colour).expand(h, w, 3),
                                     depth=self.distance.expand(h, w), extras={"marker": len(self.views)}))
        return StepOutput(tuple(views))

    @torch.inference_mode()
    def predict(self, camera, sources, *, stride, chunk_rays, features=None):
        stride = stride or 1
        h, w = camera.height // stride, camera.width // stride
        return Prediction(rgb=torch.sigmoid(self.colour).expand(h, w, 3), depth=self.distance.expand(h, w),
                          semantic=None, logits=None, stride=stride)


class ImageLoss(LossSet):
    """Colour MSE and an L1 on the images, recording what it was given."""

    needs_labels = False

    def __init__(self) -> None:
        super().__init__()
        self.inputs = []

    def forward(self, inputs):
        if not isinstance(inputs, ImageLossInputs):
            raise ConfigError("ImageLoss compares whole images; this model trains on rays")
        self.inputs.append(inputs)
        image, target = inputs.output.rgb, inputs.target_rgb
        return {"rgb": (image - target).pow(2).mean(), "image": (image - target).abs().mean()}


def trainer_with(tmp_path, model, *extra):
    composed = [item for item in extra if not item.startswith("model.loss_weights")]
    cfg = compose(["+experiment=baselines/semantic_nerf", *TINY_SCENES, "dataset.scenes=[layout_00]",
                   f"dataset.root={tmp_path / 'scenes'}", "train.steps=3", "train.log_every=1", "threads=1", *composed])
    with open_dict(cfg):  # a family's groups and terms are the ``lr`` and ``loss_weights`` sections of its config
        section = OmegaConf.to_container(cfg.model)  # semantic_nerf's lr has ``field``
        cfg.model = OmegaConf.create({**section, "lr": {**section["lr"], "colour": 0.05},
                                      "loss_weights": {"brightness": 0.5}})
        for item in extra:  # the family's own keys, set after its sections exist
            if item.startswith("model.loss_weights"):
                key, value = item.split("=", 1)
                OmegaConf.update(cfg, key, float(value), merge=False)
    components = build_components(cfg)
    components.model, components.loss = model, ImageLoss()
    return make_trainer(cfg, tmp_path / "run", components=components)


def test_a_whole_image_family_returns_images_and_its_loss_reads_images(tmp_path):
    model = FlatImage()
    trainer = trainer_with(tmp_path, model, "train.rays=7")
    result = trainer.fit(progress=False)
    inputs, view = trainer.loss.inputs[0], model.views[0]
    assert isinstance(inputs.output, ImageOutput) and inputs.output.rgb.shape == (32, 48, 3)  # not train.rays=7
    assert view.whole_image and view.pixels is None  # no pixel is drawn, no image flattened into rays
    assert torch.equal(inputs.target_rgb, view.image.permute(1, 2, 0)) and inputs.target_depth.shape == (32, 48)
    assert result.rays_per_step == 32 * 48
    assert not torch.equal(model.colour.detach(), torch.zeros(3))  # it learned


def test_callbacks_see_each_step_its_outputs_and_the_gradients_before_the_optimizer(tmp_path):
    model = FlatImage()
    trainer_with(tmp_path, model).fit(progress=False)
    assert model.seen == [("before", 0), ("after", 0), ("before", 1), ("before", 2), ("after", 2)]
    assert model.gradient_before_step == [True, True, True]
    assert [output.views[0].extras["marker"] for output in model.handed] == [1, 2, 3]  # each step's own outputs


def test_a_family_term_is_weighted_logged_and_checked_naming_the_family_and_the_term(tmp_path):
    model = FlatImage()
    trainer = trainer_with(tmp_path, model)
    result = trainer.fit(progress=False)
    entry = result.history[0]
    assert entry["brightness"] == pytest.approx(0.5 * 0.5)  # weight 0.5 x the colour's mean at the start (sigmoid 0)
    assert entry["loss"] == pytest.approx(entry["rgb"] + entry["image"] + entry["brightness"], rel=1e-5)
    broken = FlatImage()
    broken.term_scale = float("nan")
    with pytest.raises(NonFiniteError, match=r"step 0: the model 'FlatImage' .*'s own loss term 'brightness' is nan "
                                             r"\(scene 'layout_00' frame \d+\); the family made it"):
        trainer_with(tmp_path / "nan", broken).fit(progress=False)


def test_a_family_term_without_a_weight_or_a_weight_for_no_term_is_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"model.loss_weights.shine: model=semantic_nerf has no loss term 'shine' "
                                          r"\(its terms: brightness\)"):
        trainer_with(tmp_path, FlatImage(), "model.loss_weights.shine=1")
    with pytest.raises(ConfigError, match=r"model.loss_weights.brightness=-1.0: expected a finite weight >= 0"):
        trainer_with(tmp_path, FlatImage(), "model.loss_weights.brightness=-1")


def test_a_family_names_its_own_learning_rate_groups(tmp_path):
    trainer = trainer_with(tmp_path, FlatImage(), "model.lr.field=0.003")
    rates = {group["name"]: group["lr"] for group in trainer.optimizer.param_groups}
    assert rates == {"colour": 0.05, "field": 0.003}


def test_a_group_without_a_rate_is_refused_naming_it(tmp_path):
    class Unrated(FlatImage):
        def parameter_groups(self):
            return {"colour": [self.colour], "depth": [self.distance]}

    with pytest.raises(ConfigError, match=r"model Unrated trains a parameter group 'depth' that model.lr has no rate "
                                          r"for; model.lr has: field, grid, colour"):
        trainer_with(tmp_path, Unrated())


def test_a_parameter_in_no_group_is_refused_naming_it(tmp_path):
    with pytest.raises(ConfigError, match=r"model FlatImage: 1 trainable parameter\(s\) .* \(first: 'stray'\)"):
        trainer_with(tmp_path, FlatImage(stray=True))


def test_a_ray_batch_is_refused_by_an_image_term():
    from gpnerf_core.testing.inputs import loss_inputs

    with pytest.raises(ConfigError, match="compares whole images"):
        ImageLoss()(loss_inputs(semantics=False, sample_semantics=False))


class BrokenFlat(FlatImage):
    """FlatImage with one contract breach: depth ``[R, 1]``, NaN colour, or a decoded family without logits."""

    def __init__(self, breach: str) -> None:
        super().__init__()
        self.breach = breach

    @property
    def semantic_output(self):
        from gpnerf_core import Predicts, SemanticMode, SemanticOutput

        if self.breach == "no logits":
            return SemanticOutput(Predicts.CLASSES, SemanticMode.DECODED, 4)
        return None

    def forward(self, batch, *, semantics, sample_semantics=False):
        output = super().forward(batch, semantics=semantics)
        view = output.views[0]
        if self.breach == "depth":
            view = ImageOutput(rgb=view.rgb, depth=view.depth[..., None])
        elif self.breach == "nan":
            view = ImageOutput(rgb=view.rgb * float("nan"), depth=view.depth)
        return StepOutput((view, *output.views[1:]))


class SemanticLoss(ImageLoss):
    needs_semantics = True


@pytest.mark.parametrize("breach, error, message", [
    ("depth", "PluginError", r"model 'BrokenFlat' \(plugin unknown unknown\) returned image depth \[32, 48, 1\]; the "
                             r"ModelFamily contract is \[32, 48\] \(forward\)"),
    ("nan", "NonFiniteError", r"step 0: model 'BrokenFlat' .* rendered image rgb that is not finite \(NaN or Inf\) "
                              r"\(scene 'layout_00' frame \d+\); training stopped"),
    ("no logits", "ConfigError", r"model 'BrokenFlat' .* says its semantic output is decoded by a head "
                                 r"\(SemanticMode.DECODED\) but its forward\(semantics=True\) gave no logits"),
])
def test_a_family_breaking_the_contract_stops_the_run_naming_it(tmp_path, breach, error, message):
    import gpnerf_core.errors as errors

    trainer = trainer_with(tmp_path, BrokenFlat(breach))
    if breach == "no logits":
        trainer.loss = SemanticLoss()
    with pytest.raises(getattr(errors, error), match=message):
        trainer.fit(progress=False)
    assert not (tmp_path / "run" / "checkpoints").exists()
