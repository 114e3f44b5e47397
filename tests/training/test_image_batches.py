"""The contract's image-space side: a family that trains on whole images (every pixel, row-major), leaves the
ray-marching internals out, names its own learning-rate groups, sees the step through callbacks, and has every
trainable parameter in exactly one group."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf, open_dict
from torch import nn

from gpnerf_core import (
    ConfigError,
    LossSet,
    ModelFamily,
    Prediction,
    RenderedRays,
    StepOutput,
    TrainingBatch,
    TrainingCallback,
    TrainingPhase,
    ViewOutput,
)
from gpnerf_core.config.compose import compose
from gpnerf_core.model.build import build_components
from pipeline_check import TINY_SCENES, make_trainer


class FlatImage(ModelFamily):
    """One learned colour everywhere, at a learned depth: the smallest family that renders whole images."""

    generalizable = False
    accepts_head = False
    trains_on = TrainingBatch.IMAGES

    def __init__(self, *, stray: bool = False) -> None:
        super().__init__()
        self.colour = nn.Parameter(torch.zeros(3))
        self.distance = nn.Parameter(torch.ones(1))
        self.stray = nn.Parameter(torch.zeros(1)) if stray else None
        self.seen: list[tuple[str, int]] = []
        self.gradient_before_step: list[bool] = []
        self.views = []

    @property
    def semantic_output(self):
        return None

    def parameter_groups(self):
        return {"colour": [self.colour], "field": [self.distance]}

    def training_callbacks(self):
        def before(state):
            self.seen.append(("before", state.step))

        def after_backward(state):
            self.gradient_before_step.append(self.colour.grad is not None)

        def after(state):
            self.seen.append(("after", state.step))

        return (TrainingCallback(TrainingPhase.BEFORE_STEP, before),
                TrainingCallback(TrainingPhase.AFTER_BACKWARD, after_backward),
                TrainingCallback(TrainingPhase.AFTER_STEP, after, every=2))

    def forward(self, batch, *, semantics, sample_semantics=False):
        views = []
        for view in batch.views:
            self.views.append(view)
            rays = view.num_rays
            rendered = RenderedRays(rgb=torch.sigmoid(self.colour).expand(rays, 3),
                                    depth=self.distance.expand(rays))
            views.append(ViewOutput(coarse=rendered, fine=None))
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
        self.inputs.append(inputs)
        image, target = inputs.as_image(inputs.last.rgb), inputs.as_image(inputs.target_rgb)
        return {"rgb": (inputs.last.rgb - inputs.target_rgb).pow(2).mean(), "image": (image - target).abs().mean()}


def trainer_with(tmp_path, model, *extra):
    cfg = compose(["+experiment=baselines/semantic_nerf", *TINY_SCENES, "dataset.scenes=[layout_00]",
                   f"dataset.root={tmp_path / 'scenes'}", "train.steps=3", "train.log_every=1", "threads=1", *extra])
    with open_dict(cfg):  # a family's groups are the ``lr`` section of its config (semantic_nerf's has ``field``)
        section = OmegaConf.to_container(cfg.model)
        cfg.model = OmegaConf.create({**section, "lr": {**section["lr"], "colour": 0.05}})
    components = build_components(cfg)
    components.model, components.loss = model, ImageLoss()
    return make_trainer(cfg, tmp_path / "run", components=components)


def test_a_whole_image_family_trains_on_every_pixel_and_its_loss_reads_images(tmp_path):
    model = FlatImage()
    trainer = trainer_with(tmp_path, model, "train.rays=7")
    result = trainer.fit(progress=False)
    inputs, view = trainer.loss.inputs[0], model.views[0]
    height, width = inputs.image_size
    assert (height, width) == (32, 48) and inputs.target_rgb.shape == (height * width, 3)  # not train.rays=7
    assert view.whole_image and torch.equal(view.pixels[: width + 1, 0], torch.arange(width + 1.0) % width)
    assert torch.equal(inputs.as_image(inputs.target_rgb), view.image)  # row-major pixels make the image back
    assert result.rays_per_step == height * width
    assert not torch.equal(model.colour.detach(), torch.zeros(3))  # it learned


def test_callbacks_see_each_step_and_the_gradients_before_the_optimizer(tmp_path):
    model = FlatImage()
    trainer_with(tmp_path, model).fit(progress=False)
    assert model.seen == [("before", 0), ("after", 0), ("before", 1), ("before", 2), ("after", 2)]
    assert model.gradient_before_step == [True, True, True]


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

    with pytest.raises(ConfigError, match="trains on whole images"):
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
            view = ViewOutput(coarse=RenderedRays(rgb=view.coarse.rgb, depth=view.coarse.depth[:, None]), fine=None)
        elif self.breach == "nan":
            view = ViewOutput(coarse=RenderedRays(rgb=view.coarse.rgb * float("nan"), depth=view.coarse.depth),
                              fine=None)
        return StepOutput((view, *output.views[1:]))


class SemanticLoss(ImageLoss):
    needs_semantics = True


@pytest.mark.parametrize("breach, error, message", [
    ("depth", "PluginError", r"model 'BrokenFlat' \(plugin unknown unknown\) returned coarse.depth \[1536, 1\]; the "
                             r"ModelFamily contract is \[1536\] \(forward\)"),
    ("nan", "NonFiniteError", r"step 0: model 'BrokenFlat' .* rendered coarse.rgb that is not finite \(NaN or Inf\) "
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
