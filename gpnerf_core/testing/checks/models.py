"""Checks of model families: ``forward(StepBatch) -> StepOutput`` in training, ``predict(camera, sources) ->
Prediction`` on a whole view, what they say about themselves (``capabilities``, ``semantic_output``,
``parameter_groups``), and their hooks in a few training steps with density control made to act (callbacks, their
own loss terms, an optimizer that follows a change of size, finite weights), then what follows training: the Gaussians
``export`` writes, the weights saved and reloaded, the optimizer state resumed.

The kit builds a family with the parts its config declares (``gpnerf_core.part``; their options from the family's
config under check and the kit's ``configs``, else their defaults) and the kit's head (``inputs.KIT_HEAD``), at 3
classes, and renders a synthetic 32 x 48 scene seen from two source views (a per-scene family
is first ``initialise``d with that scene, ``inputs.model_scene``).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import torch
from torch import Tensor, nn

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.geometry.gaussians.scene import SCENE_FIELDS, scene_problem
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.interfaces.model import ModelFamily, SemanticMode, SemanticOutput, TrainingBatch, capability_problems
from gpnerf_core.interfaces.training import TrainingPhase, TrainingState
from gpnerf_core.testing.checks.common import (
    CheckFailed,
    Subject,
    call,
    check_round_trip,
    expect,
    expect_finite,
    expect_tensor,
    shape,
    total,
)
from gpnerf_core.testing.inputs import KIT_CLASSES, model_batch, model_scene, model_view
from gpnerf_core.model.weights import check_finite_model, load_weights, non_finite_tensor
from gpnerf_core.runtime.ply import write_ply
from gpnerf_core.training.optimizer import (
    check_parameter_groups as check_groups,
    learning_rates,
    make_optimizer,
    optimizer_problem,
)
from gpnerf_core.types import ImageOutput, Prediction, RenderedRays, StepOutput, ViewOutput

KIT_STEPS = 6
"""Training steps of the hooks check, and its ``train.steps``: a schedule the family scales to the run (3D Gaussian
splatting's densification) acts within them."""


def build(subject: Subject, *, head: bool) -> ModelFamily:
    return built(subject, head=head)[0]


def built(subject: Subject, *, head: bool) -> tuple[ModelFamily, set[int]]:
    """The family, and the ids of its parts' parameters (the parts are checked as components of their own kinds)."""
    parts = subject.kit_parts(head=head)
    model = subject.build(parts=parts)
    expect(isinstance(model, ModelFamily), f"built a {type(model).__name__}, expected a ModelFamily")
    if not model.capabilities.generalizable:  # as the trainer does before a per-scene family's first step
        call("hooks.initialise(the synthetic scene)", model.hooks.initialise, model_scene())
    return model, {id(p) for part in parts.built if isinstance(part, nn.Module) for p in part.parameters()}


def semantic_output(model: ModelFamily) -> SemanticOutput | None:
    output = call("reading semantic_output", lambda: model.semantic_output)
    if output is None:
        return None
    expect(isinstance(output, SemanticOutput), f"semantic_output is {type(output).__name__}, expected SemanticOutput")
    expect(isinstance(output.predicts, Predicts) and isinstance(output.mode, SemanticMode),
           f"semantic_output {output}: predicts and mode must be Predicts and SemanticMode members")
    expect(isinstance(output.num_outputs, int) and output.num_outputs >= 1,
           f"semantic_output.num_outputs is {output.num_outputs!r}, expected a positive int")
    return output


def heads(subject: Subject) -> tuple[bool, ...]:
    """Whether to build with a head: both ways, or only without one for a family that refuses heads."""
    return (False, True) if subject.takes_head else (False,)


def check_build(subject: Subject) -> None:
    """Builds with and without a head (a family with ``Capabilities(accepts_head=False)`` refuses one with a
    ConfigError); parameters start finite; ``semantic_output`` is a ``SemanticOutput`` or None, with the kit's class count for a
    class output."""
    if not subject.takes_head:
        try:
            build(subject, head=True)
        except CheckFailed as failed:
            expect("ConfigError" in str(failed) or "ConfigError" in type(failed.__cause__).__name__,
                   "capabilities.accepts_head is False but a configured head made the build fail otherwise: "
                   f"{failed}")
        else:
            raise CheckFailed("capabilities.accepts_head is False but the family built with a configured head (it "
                              "would be silently ignored): raise a ConfigError naming +head")
    if subject.takes_head:  # a configured head is used, not silently ignored
        parts = subject.kit_parts(head=True)
        with_head = subject.build(parts=parts)
        expect("head" in parts.built_kinds,
               "a head was configured (+head=unet) but the family built none, so it would be silently ignored: build "
               "it with parts.head(...), or declare Capabilities(accepts_head=False) and refuse it with a ConfigError "
               "naming +head")
        decoded = semantic_output(with_head)
        expect(decoded is not None and decoded.mode is SemanticMode.DECODED,
               f"with a head configured semantic_output.mode is {getattr(decoded, 'mode', None)}, expected "
               "SemanticMode.DECODED (the head decodes what the family renders)")
    for head in heads(subject):
        model = build(subject, head=head)
        expect_finite({f"parameter {k}": p for k, p in model.named_parameters()}, "after construction")
        output = semantic_output(model)
        if output is not None and output.predicts is Predicts.CLASSES:
            expect(output.num_outputs == KIT_CLASSES, f"semantic_output.num_outputs is {output.num_outputs} with a "
                                                      f"{KIT_CLASSES}-class dataset, expected {KIT_CLASSES}")


def family_rates(subject: Subject) -> dict[str, float]:
    """The family's learning rates as the optimizer takes them: its config's ``lr`` section (``model.lr.<group>``), with
    the kit's config on top."""
    lr = getattr(subject.entry.spec.config(), "lr", None)
    rates = dataclasses.asdict(lr) if dataclasses.is_dataclass(lr) else dict(lr or {})
    return learning_rates({**rates, **dict(subject.node().get("lr") or {})})


def check_parameter_groups(subject: Subject) -> None:
    """``parameter_groups()`` keeps the optimizer's rule (``training.optimizer.check_parameter_groups``, the same
    check): every trainable parameter in exactly one learning-rate group, and every group a rate in the family's
    ``model.lr``."""
    model = build(subject, head=subject.takes_head)
    groups = call("parameter_groups()", model.parameter_groups)
    expect(isinstance(groups, dict), f"parameter_groups() returned {type(groups).__name__}, expected a dict")
    rates = call("reading the family's learning rates (its config's lr section)", family_rates, subject)
    call("the optimizer's check of parameter_groups()", check_groups, model, groups, rates)


def _pass_outputs(name: str, rendered: RenderedRays, rays: int, classes: int | None) -> dict[str, Tensor]:
    expect(isinstance(rendered, RenderedRays), f"{name} is {type(rendered).__name__}, expected RenderedRays")
    out = {f"{name}.rgb": expect_tensor(rendered.rgb, f"{name}.rgb", [rays, 3])}
    if rendered.weights is not None:  # a ray-marching family's samples; a rasterizing one has none
        samples = expect_tensor(rendered.weights, f"{name}.weights").shape[-1]
        expect_tensor(rendered.weights, f"{name}.weights", [rays, samples])
        out[f"{name}.weights"] = rendered.weights
        depths = rendered.samples.depths if rendered.samples is not None else None
        expect(depths is not None and tuple(depths.shape) == (rays, samples),
               f"{name}.weights {shape(rendered.weights)} but samples.depths "
               f"{shape(depths) if depths is not None else 'None'}; expected [{rays}, {samples}]")
    else:
        expect(rendered.samples is None and rendered.sample_semantic is None,
               f"{name}.weights is None but samples or sample_semantic is not: a pass has samples with weights or none")
    out[f"{name}.depth"] = expect_tensor(rendered.depth, f"{name}.depth", [rays])
    if rendered.semantic is not None:
        out[f"{name}.semantic"] = expect_tensor(rendered.semantic, f"{name}.semantic")
    if rendered.sample_semantic is not None:
        out[f"{name}.sample_semantic"] = rendered.sample_semantic
    if rendered.logits is not None:
        expect(classes is not None, f"{name}.logits {shape(rendered.logits)} from a model without semantic_output")
        out[f"{name}.logits"] = expect_tensor(rendered.logits, f"{name}.logits", [rays, classes])
    return out


def _view_outputs(view: ViewOutput, rays: int, image: tuple[int, int], output: SemanticOutput | None) -> dict[str, Tensor]:
    expect(isinstance(view, ViewOutput), f"forward gave a {type(view).__name__} per view, expected ViewOutput")
    classes = output.num_outputs if output is not None else None
    out = _pass_outputs("coarse", view.coarse, rays, classes)
    if view.fine is not None:
        out |= _pass_outputs("fine", view.fine, rays, classes)
    if view.logits is not None:
        expect(output is not None, f"logits {shape(view.logits)} from a model without semantic_output")
        out["logits"] = expect_tensor(view.logits, "logits", [1, output.num_outputs, *image])
    if view.teacher_at_rays is not None:
        out["teacher_at_rays"] = view.teacher_at_rays
    if output is not None:
        if output.mode is SemanticMode.DECODED:
            expect(view.logits is not None, "semantic_output.mode is DECODED but forward(semantics=True) gave no logits")
        else:
            expect(view.last.logits is not None,
                   "semantic_output.mode is LABEL_RENDERING but forward(semantics=True) gave no per-ray logits")
    return out


def _image_outputs(view: ImageOutput, image: tuple[int, int], output: SemanticOutput | None) -> dict[str, Tensor]:
    expect(isinstance(view, ImageOutput), f"forward gave a {type(view).__name__} per view; a family that trains on "
                                          "whole images (capabilities.trains_on IMAGES) returns ImageOutput")
    classes = output.num_outputs if output is not None else None
    out = {"image.rgb": expect_tensor(view.rgb, "image.rgb", [*image, 3]),
           "image.depth": expect_tensor(view.depth, "image.depth", list(image))}
    if view.alpha is not None:
        out["image.alpha"] = expect_tensor(view.alpha, "image.alpha", list(image))
    for name in ("scores", "logits"):
        value = getattr(view, name)
        if value is not None:
            expect(classes is not None, f"image.{name} {shape(value)} from a model without semantic_output")
            out[f"image.{name}"] = expect_tensor(value, f"image.{name}", [1, classes, *image])
    for name in ("semantic", "teacher_map"):
        value = getattr(view, name)
        if value is not None:
            expect(isinstance(value, Tensor) and value.dim() == 4 and value.shape[0] == 1,
                   f"image.{name} is {shape(value)}, expected [1, C, h, w]")
            out[f"image.{name}"] = value
    if output is not None:
        if output.mode is SemanticMode.DECODED:
            expect(view.logits is not None, "semantic_output.mode is DECODED but forward(semantics=True) gave no logits")
        else:
            expect(view.scores is not None,
                   "semantic_output.mode is LABEL_RENDERING but forward(semantics=True) gave no per-pixel scores")
    return out


def check_forward(subject: Subject) -> None:
    """Training: one ``ViewOutput`` per target view, every pass's colour ``[R, 3]``, weights ``[R, S]``, depth ``[R]``,
    the semantic scores its ``semantic_output`` promises, finite gradients, and (with a head configured) a gradient to
    every parameter of the family's own (its parts are checked as components of their kinds)."""
    for head in heads(subject):
        model, part_parameters = built(subject, head=head)
        model.train()
        output = semantic_output(model)
        whole = model.capabilities.trains_on is TrainingBatch.IMAGES
        batch = model_batch(sources=model.capabilities.generalizable, whole_images=whole)
        result = call("forward(batch of 2 views, semantics=True, sample_semantics=True)", model, batch,
                      semantics=output is not None, sample_semantics=output is not None)
        expect(isinstance(result, StepOutput) and len(result.views) == len(batch.views),
               f"forward returned {type(result).__name__}, expected a StepOutput with {len(batch.views)} views")
        outputs: dict[str, Tensor] = {}
        for index, (view, target) in enumerate(zip(result.views, batch.views)):
            found = (_image_outputs(view, target.camera.image_size, output) if whole
                     else _view_outputs(view, target.num_rays, target.camera.image_size, output))
            outputs |= {f"view {index} {name}": tensor for name, tensor in found.items()}
        expect_finite(outputs, "in training mode")
        differentiable = {k: v for k, v in outputs.items() if not k.endswith((".depth", ".alpha"))}
        if model.capabilities.segments_image and model.capabilities.loss_terms:
            # a 2D model renders nothing to differentiate: what trains it is its own loss terms
            state = TrainingState(step=0, total_steps=1, optimizer=None, batch=batch, outputs=result)
            own = call("hooks.loss_terms after forward", model.hooks.loss_terms, state,
                       frozenset(model.capabilities.loss_terms))
            differentiable |= {f"loss term {name}": value for name, value in own.items()}
        scalar = total(differentiable)
        expect(isinstance(scalar, Tensor) and scalar.requires_grad, "no output of forward requires grad")
        call("backward of the sum of the outputs", scalar.backward)
        expect_finite({f"gradient of {n}": p.grad for n, p in model.named_parameters() if p.grad is not None},
                      "after a backward of the outputs")
        # The family's own parameters all learn from what it renders (with a head its whole semantic path is in use);
        # a part may be partly unused (an extractor's semantic branch under a colour-only model).
        own = [n for n, p in model.named_parameters() if p.requires_grad and id(p) not in part_parameters]
        missing = [n for n in own if dict(model.named_parameters())[n].grad is None]
        expect(not missing or (not head and subject.takes_head),
               f"no gradient reached the model's own {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''} "
               f"({len(missing)} of {len(own)}) after a backward of the sum of its outputs")


def _prediction(model: ModelFamily, stride: int) -> Prediction:
    camera, sources = model_view(sources=model.capabilities.generalizable)
    if model.capabilities.segments_image:  # a 2D model segments the real image, which evaluation gives it
        camera = dataclasses.replace(camera, image=model_scene().load_frame(1).rgb)
    what = f"predict(camera {camera.height}x{camera.width}, {'2 source views' if sources else 'no sources'}, stride={stride})"
    prediction = call(what, model.predict, camera, sources, stride=stride, chunk_rays=97)
    expect(isinstance(prediction, Prediction), f"{what} returned {type(prediction).__name__}, expected Prediction")
    return prediction


def check_predict(subject: Subject) -> None:
    """A whole view: colour ``[h, w, 3]`` and depth ``[h, w]`` on the ``stride`` grid (h = H / stride), scores
    ``[1, K, H, W]`` at the image's size when the model has a semantic output; finite; the same twice in eval mode."""
    for head in heads(subject):
        model = build(subject, head=head).eval()
        output = semantic_output(model)
        for stride in (0, 4):
            first, second = _prediction(model, stride), _prediction(model, stride)
            s = first.stride
            expect(isinstance(s, int) and s >= 1 and (stride == 0 or s == stride),
                   f"predict(stride={stride}) reports stride {s!r}")
            h, w = 32 // s, 48 // s
            found = {"rgb": expect_tensor(first.rgb, "rgb", [h, w, 3]), "depth": expect_tensor(first.depth, "depth", [h, w])}
            if output is not None:
                found["logits"] = expect_tensor(first.logits, "logits", [1, output.num_outputs, 32, 48])
            if first.semantic is not None:
                found["semantic"] = expect_tensor(first.semantic, "semantic")
                expect(list(first.semantic.shape[1:]) == [h, w], f"semantic {shape(first.semantic)}, expected [C, {h}, {w}]")
            expect_finite(found, f"in eval mode at stride {stride}")
            for name, tensor in found.items():
                again = getattr(second, name)
                if not torch.equal(tensor, again):
                    raise CheckFailed(f"predict gave different {name} twice in eval mode: it must be deterministic")


def check_capabilities(subject: Subject) -> None:
    """The family's ``capabilities`` record holds (``capability_problems``): every capability it declares is
    implemented, every optional member it implements is declared. The registry refuses such a family already when it
    can see its class (a factory that is the class, or annotated with it); this is the check of the class built."""
    model = build(subject, head=False)
    problems = capability_problems(type(model))
    expect(not problems, "; ".join(problems))


KIT_DENSITY = {"schedule_steps": KIT_STEPS, "densify_from": 1, "densify_every": 2, "densify_until": KIT_STEPS,
               "opacity_reset_every": 1000, "densify_grad_threshold": 1e-12}
"""Config fields the hooks check sets where the family's config has them (``GaussianSceneConfig``'s): density control
acts as the steps' schedule makes it due, at the 2nd and 4th step, on every Gaussian a view saw (any gradient), so a
family that ``changes_size`` changes size within the steps; no opacity reset (the synthetic scene's cameras are 0.1 m
apart: world-size pruning after one would remove every Gaussian). A family with its own schedule makes it act within
``KIT_STEPS`` steps through the kit's ``configs``."""


def densifying(subject: Subject) -> Subject:
    """``subject`` with ``KIT_DENSITY`` over its config, for the fields its config has."""
    fields = {f.name for f in dataclasses.fields(subject.entry.spec.config)}
    forced = {key: value for key, value in KIT_DENSITY.items() if key in fields}
    return dataclasses.replace(subject, config={**subject.config, **forced}) if forced else subject


def check_training_hooks(subject: Subject) -> None:
    """``KIT_STEPS`` training steps through the family's hooks as the trainer runs them (``train.steps`` =
    ``KIT_STEPS``, density control forced due: ``KIT_DENSITY``): its callbacks at their phases, told the step and its
    outputs; its own loss terms (every name of ``capabilities.loss_terms``, a finite scalar each step, its gradient
    reaching the model); after every step an optimizer that still steps every parameter with moments of its shape
    (``training.optimizer.optimizer_problem``, the trainer's rule: a densification that replaced parameters without
    the optimizer fails here), every weight finite (the trainer writes no checkpoint otherwise), and the shapes kept
    unless ``capabilities.changes_size``; a family that declares it changes size within the steps. Then what follows
    training: its Gaussians as ``export`` writes them (``_check_gaussians``), its weights saved, reloaded and equal,
    its optimizer state resumed (``_check_reload``)."""
    subject = densifying(subject)
    model = build(subject, head=subject.takes_head).train()
    capabilities = model.capabilities
    groups = call("parameter_groups()", model.parameter_groups)
    options = call(f"hooks.optimizer_options({KIT_STEPS})", model.hooks.optimizer_options, KIT_STEPS)
    optimizer = call("building Adam over its groups", make_optimizer, model, dict.fromkeys(groups, 1e-3), options)
    callbacks = call("hooks.callbacks()", lambda: tuple(model.hooks.callbacks()))
    wanted = frozenset(capabilities.loss_terms)
    output_kind = semantic_output(model)
    whole = capabilities.trains_on is TrainingBatch.IMAGES

    def run(phase: TrainingPhase, state: TrainingState) -> None:
        for callback in callbacks:
            if callback.phase is phase and callback.due(state.step):
                call(f"its {phase.value} callback at step {state.step}", callback.run, state)

    shapes = {name: tuple(p.shape) for name, p in model.named_parameters()}
    resized = False
    for step in range(KIT_STEPS):
        batch = model_batch(sources=capabilities.generalizable, whole_images=whole, views=1)
        state = TrainingState(step=step, total_steps=KIT_STEPS, optimizer=optimizer, batch=batch)
        run(TrainingPhase.BEFORE_STEP, state)
        result = call(f"forward at step {step}", model, batch, semantics=output_kind is not None)
        state = TrainingState(step=step, total_steps=KIT_STEPS, optimizer=optimizer, batch=batch, outputs=result)
        view = result.views[0]
        rendered = view.rgb if isinstance(view, ImageOutput) else view.last.rgb
        total = rendered.float().square().mean()
        if wanted:
            terms = call(f"hooks.loss_terms at step {step}", model.hooks.loss_terms, state, wanted)
            expect(isinstance(terms, dict) and set(wanted) <= set(terms),
                   f"hooks.loss_terms at step {step} gave {sorted(terms) if isinstance(terms, dict) else terms!r}; "
                   f"expected every term capabilities.loss_terms declares ({', '.join(sorted(wanted))})")
            for name in sorted(wanted):
                value = terms[name]
                expect(isinstance(value, Tensor) and value.numel() == 1,
                       f"loss term {name!r} at step {step} is {shape(value)}, expected a scalar tensor")
                expect(bool(torch.isfinite(value.detach()).all()),
                       f"loss term {name!r} is {float(value.detach())} at step {step}: the family's own term is not "
                       "finite (the trainer stops the run on it)")
                total = total + value.reshape(()).float()
        run(TrainingPhase.BEFORE_BACKWARD, state)
        optimizer.zero_grad(set_to_none=True)
        call(f"backward at step {step}", total.backward)
        run(TrainingPhase.AFTER_BACKWARD, state)
        optimizer.step()
        run(TrainingPhase.AFTER_STEP, state)
        problem = optimizer_problem(model, optimizer, subject.name)
        expect(problem is None, f"after step {step}: {problem}")
        found = non_finite_tensor(model)
        expect(found is None, f"after step {step}: {found}; the trainer refuses to write a checkpoint of it "
                              "(check_finite_model) and stops the run")
        now = {n: tuple(p.shape) for n, p in model.named_parameters()}
        resized = resized or now != shapes
        if not capabilities.changes_size:
            changed = [n for n in {**shapes, **now} if shapes.get(n) != now.get(n)]
            expect(not changed, f"after step {step} parameter {changed[0] if changed else ''!r} changed its shape, but "
                                "capabilities.changes_size is False: declare it (the trainer refuses a change of "
                                "shape otherwise, and train.ema_decay with it; checkpoints load through "
                                "hooks.resize_to)")
    if capabilities.changes_size:
        forced = ", ".join(f"model.{k}={KIT_DENSITY[k]}" for k in KIT_DENSITY if k in subject.config)
        how = (f"with {forced}" if forced
               else "its config has none of the kit's density keys: give the kit configs that make it act")
        expect(resized, f"capabilities.changes_size is True but no parameter changed size in {KIT_STEPS} steps "
                        f"({how}): its density control never acted, so the kit could not check that the optimizer "
                        "follows it")
    model.eval()
    if capabilities.gaussians and not capabilities.generalizable:
        _check_gaussians(model, f"after {KIT_STEPS} training steps")
    _check_reload(subject, model, optimizer, options)


def _check_gaussians(model: ModelFamily, when: str) -> None:
    """A per-scene family's ``scene_gaussians`` (what ``export`` writes, ``view`` draws) keeps ``scene_problem``
    (export's rule: one row per Gaussian in every column, the documented shapes, labels -1 or an output of
    ``semantic_output``), is finite, and is written to a PLY in a temporary folder as ``export`` writes it, one row
    per Gaussian."""
    scene = model_scene()
    with torch.no_grad():
        splats = call("scene_gaussians(None, ...)", model.scene_gaussians, None, near=scene.near, far=scene.far)
    output = model.semantic_output
    problem = scene_problem(splats, output.num_outputs if output is not None else 0)
    expect(problem is None, f"{when}: scene_gaussians: {problem} (export refuses it)")
    for field in SCENE_FIELDS[:-1]:
        expect(bool(torch.isfinite(getattr(splats, field)).all()),
               f"{when}: scene_gaussians' {field} holds NaN or Inf")
    with tempfile.TemporaryDirectory(prefix="gpnerf-kit-") as folder:
        path = Path(folder) / "gaussians.ply"
        call("writing scene_gaussians as export does (gaussians.ply)", write_ply, path,
             columns=splats.ply_columns())
        data = path.read_bytes()
    header, _, body = data.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    count = next((int(line.split()[2]) for line in lines if line.startswith("element vertex")), -1)
    expect(count == splats.count, f"{when}: the exported gaussians.ply holds {count} vertices for {splats.count} "
                                  "Gaussians")


def _check_reload(subject: Subject, model: ModelFamily, optimizer: torch.optim.Optimizer,
                  options: object) -> None:
    """The trained family's weights saved to a file and loaded into a fresh build as a checkpoint is
    (``load_weights``: ``hooks.resize_to`` first for a family that ``changes_size``) come back bit for bit; its
    optimizer's state loads into the fresh build's optimizer and fits its parameters (``optimizer_problem``, which
    resume checks); the trainer's guard before a checkpoint (``check_finite_model``) sees a NaN put in a parameter."""
    with tempfile.TemporaryDirectory(prefix="gpnerf-kit-") as folder:
        path = Path(folder) / "weights.pt"
        call("torch.save(model.state_dict())", torch.save, model.state_dict(), path)
        weights = torch.load(path, map_location="cpu", weights_only=True)
    fresh = build(subject, head=subject.takes_head)
    call("loading its saved weights into a fresh build (load_weights, as resume and eval do)", load_weights, fresh,
         weights, "the kit's saved weights")
    reloaded = fresh.state_dict()
    for key, value in model.state_dict().items():
        again = reloaded.get(key)
        expect(again is not None and again.shape == value.shape and torch.equal(again.cpu(), value.cpu()),
               f"tensor {key!r} is not the same after a save and reload into a fresh build "
               f"({shape(value)} -> {shape(again) if again is not None else 'missing'})")
    groups = call("parameter_groups() of the reloaded build", fresh.parameter_groups)
    resumed = call("building Adam over the reloaded build's groups", make_optimizer, fresh,
                   dict.fromkeys(groups, 1e-3), options)
    call("loading the optimizer's state into the reloaded build's (as resume does)", resumed.load_state_dict,
         optimizer.state_dict())
    problem = optimizer_problem(fresh, resumed, subject.name)
    expect(problem is None, f"after a save and reload, the optimizer state resumed does not fit: {problem}")
    name, parameter = next(((n, p) for n, p in fresh.named_parameters() if p.is_floating_point() and p.numel()),
                           (None, None))
    if parameter is None:
        return
    with torch.no_grad():
        parameter.fill_(float("nan"))
    try:
        check_finite_model(fresh, subject.name, "the kit's NaN")
    except NonFiniteError as exc:
        expect(repr(name) in str(exc), f"a NaN put in parameter {name!r} was refused naming another tensor: {exc}")
    else:
        raise CheckFailed(f"a NaN put in parameter {name!r} was not seen by the checkpoint guard (check_finite_model "
                          "reads state_dict(): the family's state_dict leaves it out)")


CHECKS = {
    "build": check_build,
    "capabilities": check_capabilities,
    "parameter groups": check_parameter_groups,
    "forward": check_forward,
    "training hooks": check_training_hooks,
    "predict": check_predict,
    "config round trip": check_round_trip,
}
