"""The training loop: sample the step's target views, forward, loss, backward, optimizer step.

One process, or one of N under torchrun: the model is wrapped in ``DistributedDataParallel`` (gradients
averaged over processes), each process trains on its share of the global batch of target views, and rank 0
alone writes checkpoints, curves and the progress bar.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import sys
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import torch
from torch import Tensor
from torch.nn.parallel import DistributedDataParallel

from gpnerf_core.interfaces.model import ModelFamily, TrainingBatch
from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase, TrainingState
from gpnerf_core.model.build import Components
from gpnerf_core.runtime.device import autocast, check_precision, peak_memory_mb
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError, NonFiniteError, PluginError
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.features.field import TERM as FEATURE_TERM, distillation_term
from gpnerf_core.runtime.profiling import stage
from gpnerf_core.model.output_checks import check_step_output
from gpnerf_core.model.checkpoint import RunRecord, check_resume_config, checkpoint_sections, save_checkpoint
from gpnerf_core.model.trained import TrainedModel, load_trained
from gpnerf_core.model.weights import check_finite_model, load_weights
from gpnerf_core.training.interrupt import StopNow, StopRequest, TrainingInterrupted
from gpnerf_core.training.loggers import ScalarLogger
from gpnerf_core.training.resume import checkpoint_path, prune_checkpoints
from gpnerf_core.training.sampler import StepSampler
from gpnerf_core.training.optimizer import learning_rates, make_optimizer, make_scheduler, optimizer_problem
from gpnerf_core.training.schedule import lr_factor
from gpnerf_core.training.weight_average import WeightAverage
from gpnerf_core.types import (
    ImageLossInputs, ImageOutput, LossInputs, RenderedRays, StepBatch, StepOutput, TargetView, ViewOutput,
)
from gpnerf_core.runtime.finite import all_finite


@dataclass
class TrainResult:
    """What ``Trainer.fit`` did.

    Attributes:
        steps: the step reached (where a callback stopped the loop: that step); seconds: training time including
            earlier runs of a resumed run.
        rays_per_second: rays over all processes per second of this run.
        world_size, targets_per_rank, rays_per_step: the layout of the global batch (``rays_per_step`` is
            summed over processes and target views).
    """

    steps: int
    seconds: float
    rays_per_second: float
    world_size: int
    targets_per_rank: int
    rays_per_step: int
    history: list[dict[str, float]] = field(default_factory=list)
    checkpoint: Path | None = None
    stopped: str | None = None
    """Why the loop ended before ``until`` (``Trainer.request_stop``'s reason, one line); None: it reached it."""

    def metrics(self, train: Any, backend: str | None) -> dict[str, Any]:
        """The ``train`` section of a run's ``metrics.json`` (``train``: the config's ``train`` group; ``backend``:
        the process group's, None in one process)."""
        return {
            "steps": self.steps,
            "seconds": round(self.seconds, 2),
            "rays_per_second": round(self.rays_per_second, 1),
            "final_loss": self.history[-1]["loss"] if self.history else None,
            "checkpoint": str(self.checkpoint) if self.checkpoint else None,
            "world_size": self.world_size,
            "targets_per_step": int(train.targets_per_step),
            "targets_per_rank": self.targets_per_rank,
            "rays_per_step": self.rays_per_step,
            "backend": backend,
            "precision": str(train.precision),
        }


def loss_inputs(view: TargetView, output: ViewOutput | ImageOutput, ignore_index: int) -> LossInputs | ImageLossInputs:
    """What a loss set reads for one target view: a ray family's outputs with the ground truth at its rays
    (``LossInputs``), or the images of a family that renders whole images with the target images
    (``ImageLossInputs``)."""
    if isinstance(output, ImageOutput):
        semantic_outputs = output.logits is not None or output.scores is not None
        return ImageLossInputs(
            output=output,
            target_rgb=view.image.permute(1, 2, 0),
            target_depth=view.depth,
            labels=view.labels if semantic_outputs else None,
            ignore_index=ignore_index,
            instances=view.instances if semantic_outputs else None,
            valid=view.valid,
        )
    rows, cols = view.pixels[:, 1].long(), view.pixels[:, 0].long()
    return LossInputs(
        coarse=output.coarse,
        fine=output.fine,
        target_rgb=view.image[:, rows, cols].T,
        target_depth=view.depth[rows, cols],
        logits=output.logits,
        labels=view.labels[None] if output.logits is not None else None,
        teacher_at_rays=output.teacher_at_rays,
        ignore_index=ignore_index,
        instances=view.instances[None] if output.logits is not None and view.instances is not None else None,
        labels_at_rays=view.labels[rows, cols] if output.last.logits is not None else None,
        instances_at_rays=(view.instances[rows, cols]
                           if output.last.logits is not None and view.instances is not None else None),
    )


def family_term_weights(family: str, model: ModelFamily, weights: Mapping[str, Any] | None) -> dict[str, float]:
    """The weight of each of the family's own loss terms (``Capabilities.loss_terms``) from ``model.loss_weights``:
    a ConfigError naming the family and the key when a term has no weight, a weight names no term of the family, or a
    weight is not a finite number >= 0. Terms weighted 0 are left out."""
    declared = model.capabilities.loss_terms
    given = dict(weights or {})
    for name in declared:
        if name not in given:
            raise ConfigError(f"model={family} has its own loss term {name!r} but its config gives no weight for it: "
                              f"expected model.loss_weights.{name} (a number >= 0)")
    result = {}
    for name, value in given.items():
        if name not in declared:
            known = ", ".join(declared) or "none"
            raise ConfigError(f"model.loss_weights.{name}: model={family} has no loss term {name!r} (its terms: "
                              f"{known})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ConfigError(f"model.loss_weights.{name}={value!r}: expected a finite weight >= 0")
        if value > 0:
            result[str(name)] = float(value)
    return result


def _views(batch: StepBatch) -> str:
    """``scene 'a' frame 3, ...``: the target views of a step, for errors."""
    return ", ".join(f"scene {v.scene!r} frame {v.frame}" for v in batch.views)


def _check_size_changes(family: str, ema_decay: float, world_size: int) -> None:
    """A family whose parameters change size while training (``Capabilities.changes_size``) cannot keep a weight
    average of fixed-size copies, nor run under DistributedDataParallel (which registers the parameters once)."""
    if ema_decay > 0:
        raise ConfigError(f"model={family} adds and removes parameters while it trains (densification), so no weight "
                          f"average can follow it: expected train.ema_decay=0 (got {ema_decay:g})")
    if world_size > 1:
        raise ConfigError(f"model={family} adds and removes parameters while it trains (densification), which "
                          f"DistributedDataParallel cannot follow: expected one process (got {world_size})")


def process_seed(seed: int, rank: int) -> int:
    """Seed of a process's global torch RNG (dropout): distinct per rank, fixed by (seed, rank)."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{rank}".encode()).digest()[:8], "little") >> 1


class _Clock:
    """Seconds since it started, minus the spans it was ``paused``; it stands still while paused."""

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.excluded = 0.0
        self.paused_at: float | None = None

    def seconds(self) -> float:
        now = self.paused_at if self.paused_at is not None else time.perf_counter()
        return now - self.started - self.excluded

    @contextmanager
    def paused(self) -> Iterator[None]:
        self.paused_at = time.perf_counter()
        try:
            yield
        finally:
            self.excluded += time.perf_counter() - self.paused_at
            self.paused_at = None


class Trainer:
    """Trains ``components.model`` with ``components.loss`` on the dataset's training scenes.

    Args:
        cfg: the composed config.
        components: model, loss set, dataset and view selector.
        dist: this process's place in the job (single process by default).
        run_dir: where rank 0 writes checkpoints.
        record: what the run was made from, written into every checkpoint.
        resume_from: ``cfg.train.resume`` as read already (``ResumePlan.take_read``); None: read here.
    """

    def __init__(
        self,
        cfg: Any,
        components: Components,
        *,
        dist: Distributed,
        run_dir: Path,
        record: RunRecord,
        resume_from: TrainedModel | None = None,
    ) -> None:
        if components.loss is None and not components.model.capabilities.loss_terms:
            raise ConfigError("training needs a loss set: add +loss=<name> (e.g. +loss=dgs)")
        check_precision(cfg.train.precision)
        self.cfg = cfg
        self.dist = dist
        self.device = dist.device
        self.run_dir = run_dir
        self.record = record
        self.model = components.model.to(self.device)
        self.classes = components.classes
        # None: the family trains on its own loss terms alone (a 2D detector's, computed where it samples its boxes)
        self.loss = components.loss.to(self.device) if components.loss is not None else None
        self.ignore_index = components.dataset.ignore_index
        self.frames = FrameCache(components.dataset, self.device)
        capabilities = self.model.capabilities
        self.whole_images = capabilities.trains_on is TrainingBatch.IMAGES
        self.sampler = StepSampler(
            self.frames,
            components.view_selector,
            scene_names=components.dataset.scenes("train"),
            num_source_views=int(cfg.model.num_source_views) if capabilities.generalizable else 0,
            rays_per_view=int(cfg.train.rays),
            targets_per_step=int(cfg.train.targets_per_step),
            seed=int(cfg.seed),
            rank=dist.rank,
            world_size=dist.world_size,
            whole_images=self.whole_images,
        )
        decay = float(cfg.train.ema_decay)
        if capabilities.changes_size:
            _check_size_changes(cfg.model.name, decay, dist.world_size)
        self.term_weights = family_term_weights(str(cfg.model.name), self.model, cfg.model.get("loss_weights"))
        self.feature_field = components.feature_field
        """The feature provider the model's feature field is distilled from (``+feature_provider``), or None."""
        if not capabilities.generalizable and not cfg.train.resume:
            with stage("model initialisation"):
                self.model.hooks.initialise(self.frames.scene(self.sampler.scene_names[0]))
        self.optimizer, self.scheduler = self._optimizer()
        self.callbacks = {phase: [c for c in self.model.hooks.callbacks() if c.phase is phase]
                          for phase in TrainingPhase}
        self.average = WeightAverage(self.model, decay) if decay > 0 else None
        self.last_grad_norm = 0.0
        self.step = 0
        self.history: list[dict[str, float]] = []
        self.elapsed = 0.0
        self._clock: _Clock | None = None
        """The ``fit`` in progress's training time (callbacks' time is not counted)."""
        self.notes: list[str] = []
        self._stop_reason: str | None = None
        """Why a callback asked ``fit`` to end after the current step (``request_stop``); None: go on."""
        self.loss_names: list[str] = []
        """Names of the loss set's terms, known after the first step."""
        if dist.enabled:
            torch.manual_seed(process_seed(int(cfg.seed), dist.rank))
        if cfg.train.resume:
            self._resume(Path(cfg.train.resume), resume_from)
        self._shapes = self._parameter_shapes()
        """The parameters' shapes, which a family without ``Capabilities.changes_size`` keeps (``_check_parameters``)."""
        self.wrapped: torch.nn.Module = self.model
        if dist.enabled:
            # A loss set may leave whole modules without gradient (rgb alone: no head, no FPN); DDP must then search
            # the graph every step for parameters that will never be ready. Search only when a probe step finds some.
            unused = torch.tensor(float(bool(self._parameters_without_gradient())), device=self.device)
            self.wrapped = DistributedDataParallel(
                self.model,
                device_ids=[self.device.index] if self.device.type == "cuda" else None,
                find_unused_parameters=bool(self.dist.all_reduce(unused, op="max")),
            )

    def _optimizer(self) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
        """Adam over the model's learning-rate groups and the rate schedule of each (``FamilyHooks.optimizer_options``
        where the family gives its own)."""
        cfg = self.cfg
        options = self.model.hooks.optimizer_options(int(cfg.train.steps))
        optimizer = make_optimizer(self.model, learning_rates(cfg.model.get("lr")), options)
        shared = lr_factor(
            str(cfg.train.lr_schedule),
            steps=int(cfg.train.steps),
            warmup_steps=int(cfg.train.warmup_steps),
            decay_rate=float(cfg.train.lr_decay_rate),
            decay_steps=int(cfg.train.lr_decay_steps),
        )
        return optimizer, make_scheduler(optimizer, shared, options)

    @property
    def resumed_step(self) -> int | None:
        return self.step if self.cfg.train.resume else None

    def _parameters_without_gradient(self) -> list[str]:
        """Parameters one forward/backward leaves without gradient; the sampler and RNG states are restored after."""
        sampler_state, rng_state = self.sampler.state_dict(), self._rng_state()
        batch = self.sampler.next_batch()
        with autocast(self.device, self.cfg.train.precision):
            output = self.model(
                batch, semantics=self._semantics, sample_semantics=self._sample_semantics
            )
            terms = (self._loss_terms(batch, output) | self._family_terms(self._state(batch, output))
                     | self._feature_terms(batch, output))
            total = sum(terms.values())
        total.backward()
        unused = [name for name, p in self.model.named_parameters() if p.requires_grad and p.grad is None]
        self.optimizer.zero_grad(set_to_none=True)
        self.sampler.load_state_dict(sampler_state)
        self._set_rng_state(rng_state)
        return unused

    # ---- one step ----------------------------------------------------------------------------------------------

    def train_step(self, stop: StopRequest | None = None) -> tuple[dict[str, Tensor], int, int | None]:
        """Sample, forward, loss, backward, step.

        Returns:
            ``(terms, rays, stop_signal)``: the weighted loss terms of this process (the loss set's and the family's
            own, detached), the rays (or pixels) it rendered, and the signal every process agreed to stop on (None:
            go on).
        """
        with stage("sample batch"):
            batch = self.sampler.next_batch()
        self._run_family_callbacks(TrainingPhase.BEFORE_STEP, self._state(batch, None))
        try:
            with autocast(self.device, self.cfg.train.precision):
                output = self.wrapped(
                    batch, semantics=self._semantics, sample_semantics=self._sample_semantics
                )
                check_step_output(self.model, batch, output, self._semantics, self._where("model"))
                with stage("loss"):
                    terms = self._loss_terms(batch, output)
                    family_terms = self._family_terms(self._state(batch, output)) | self._feature_terms(batch, output)
        except NonFiniteError as exc:  # a component's output (registry.guards), named where it was made
            self._stop_everywhere(f"{exc} ({_views(batch)})")
        stop_signal = self._check_and_agree(terms, family_terms, batch, stop, output)
        terms = terms | family_terms
        total: Tensor = sum(terms.values())
        state = self._state(batch, output)
        self._run_family_callbacks(TrainingPhase.BEFORE_BACKWARD, state)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        if self._run_family_callbacks(TrainingPhase.AFTER_BACKWARD, state):  # only callbacks resize mid-step
            self._check_parameters("after its after_backward callbacks")
        with stage("optimizer"):
            clip = self.cfg.train.grad_clip
            grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), clip if clip > 0 else math.inf)
            if not torch.isfinite(grad_norm):
                raise NonFiniteError(f"step {self.step}: gradient norm is {grad_norm.item()}; training stopped")
            self.optimizer.step()
            self.scheduler.step()
            if self.average is not None:
                self.average.update(self.model)
        if self._run_family_callbacks(TrainingPhase.AFTER_STEP, state):  # only callbacks resize mid-step
            self._check_parameters("after its after_step callbacks")
        self.last_grad_norm = grad_norm.detach()
        detached = {name: value.detach() for name, value in terms.items()} | {"loss": total.detach()}
        return detached, batch.num_rays, stop_signal

    def _parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        return {name: tuple(p.shape) for name, p in self.model.named_parameters()}

    def _check_parameters(self, when: str) -> None:
        """The family's parameters after its callbacks: a family that ``changes_size`` still has every parameter in
        the optimizer with moments of its shape (``optimizer_problem``), one that does not kept every shape; else a
        one-line ``PluginError`` (a densification that bypassed the optimizer would otherwise train nothing more, and
        an undeclared growth break ``train.ema_decay``'s average and every resume)."""
        name = self.cfg.model.name
        if self.model.capabilities.changes_size:
            problem = optimizer_problem(self.model, self.optimizer, str(self.cfg.model.name))
            if problem is not None:
                raise PluginError(f"step {self.step}, {when}: {problem}; training stopped")
            return
        shapes = self._parameter_shapes()
        if shapes == self._shapes:
            return
        changed = next((key for key in {**self._shapes, **shapes} if self._shapes.get(key) != shapes.get(key)))
        before, after = self._shapes.get(changed), shapes.get(changed)
        average = (f"; train.ema_decay={self.average.decay:g} keeps an average of fixed-size copies, which cannot "
                   "follow it" if self.average is not None else "")
        raise PluginError(
            f"step {self.step}, {when}: model={name} changed parameter {changed!r} from "
            f"{list(before) if before is not None else 'nothing'} to {list(after) if after is not None else 'nothing'}, "
            f"but its capabilities.changes_size is False{average}: declare Capabilities(changes_size=True) (with "
            "hooks.resize_to; train.ema_decay must then be 0)"
        )

    def _state(self, batch: StepBatch | None, output: StepOutput | None) -> TrainingState:
        """What a callback or a family term is told at this point of the step."""
        return TrainingState(step=self.step, total_steps=int(self.cfg.train.steps), optimizer=self.optimizer,
                             batch=batch, outputs=output, seconds=self.training_seconds, checkpoint=self.checkpoint,
                             request_stop=self.request_stop)

    def _run_family_callbacks(self, phase: TrainingPhase, state: TrainingState) -> bool:
        """The callbacks of ``phase`` that are due at this step and count as training time: the family's
        (``FamilyHooks.callbacks``) and the command's timed ones, in that order; whether any ran."""
        due = [c for c in self.callbacks[phase] if c.due(self.step)]
        if not due:
            return False
        with stage(f"model callbacks ({phase.value})"):
            for callback in due:
                callback.run(state)
        return True

    @property
    def _semantics(self) -> bool:
        """The loss set reads semantic outputs (False without a loss set)."""
        return self.loss is not None and self.loss.needs_semantics

    @property
    def _sample_semantics(self) -> bool:
        return self.loss is not None and self.loss.needs_sample_semantics

    def _loss_terms(self, batch: StepBatch, output: StepOutput) -> dict[str, Tensor]:
        """Each term averaged over this process's target views (so DDP's mean over processes is the global mean); none
        without a loss set."""
        if self.loss is None:
            return {}
        per_view = [
            self.loss(loss_inputs(view, out, self.ignore_index)) for view, out in zip(batch.views, output.views)
        ]
        return {name: sum(terms[name].float() for terms in per_view) / len(per_view) for name in per_view[0]}

    def _family_terms(self, state: TrainingState) -> dict[str, Tensor]:
        """The family's own loss terms of this step (``FamilyHooks.loss_terms``), each times its
        ``model.loss_weights`` weight; a term missing, undeclared or not a scalar stops the run naming the family."""
        if not self.term_weights:
            return {}
        family = self._where("model")
        found = self.model.hooks.loss_terms(state, frozenset(self.term_weights))
        if not isinstance(found, Mapping):
            raise PluginError(f"{family}: hooks.loss_terms returned {type(found).__name__}, expected a mapping of "
                              "term name to scalar tensor")
        missing = [name for name in self.term_weights if name not in found]
        if missing:
            raise PluginError(f"{family}: hooks.loss_terms gave no term {missing[0]!r}, which its capabilities "
                              "declare and model.loss_weights weighs")
        weighted = {}
        for name, weight in self.term_weights.items():
            value = found[name]
            if not isinstance(value, Tensor) or value.numel() != 1:
                shown = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise PluginError(f"{family}: its loss term {name!r} is {shown}, expected a scalar tensor")
            weighted[name] = weight * value.reshape(()).float()
        return weighted

    def _feature_terms(self, batch: StepBatch, output: StepOutput) -> dict[str, Tensor]:
        """The feature-field distillation term of this step (``train/feature_field``: ``features.weight`` times
        ``gpnerf_core.features.field.distillation_term``); none without ``+feature_provider``, with a weight of 0, or
        when the family rendered no field this step."""
        field = self.feature_field
        if field is None or not field.options.weight:
            return {}
        term = distillation_term(field, batch, output)
        return {} if term is None else {FEATURE_TERM: float(field.options.weight) * term.reshape(()).float()}

    def _check_and_agree(
        self, terms: dict[str, Tensor], family_terms: dict[str, Tensor], batch: StepBatch, stop: StopRequest | None,
        output: StepOutput,
    ) -> int | None:
        """Stop every process on a non-finite term anywhere, and agree on a stop signal, before backward."""
        bad = next((name for name, value in terms.items() if not all_finite(value)), None)
        bad_family = next((name for name, value in family_terms.items() if not all_finite(value)), None)
        flags = torch.tensor(
            [float(bad is not None or bad_family is not None), float(stop.signum or 0) if stop is not None else 0.0],
            device=self.device,
        )
        self.dist.all_reduce(flags, op="max")
        if bad is not None:
            raise NonFiniteError(
                f"step {self.step}: loss term {bad!r} is {terms[bad].item()} ({_views(batch)}) in "
                f"{self._loss_where()}; {self._non_finite_inputs(batch, output)}; training stopped"
            )
        if bad_family is not None:
            raise NonFiniteError(
                f"step {self.step}: the {self._where('model')}'s own loss term {bad_family!r} is "
                f"{family_terms[bad_family].item()} ({_views(batch)}); the family made it (hooks.loss_terms); "
                "training stopped"
            )
        if flags[0] > 0:
            raise NonFiniteError(f"step {self.step}: a loss term or a component's output is not finite on another "
                                 "process; training stopped")
        return int(flags[1]) or None

    def _stop_everywhere(self, reason: str) -> None:
        """Raise ``reason`` here, after telling every other process to stop (the flag ``_check_and_agree`` reduces)."""
        self.dist.all_reduce(torch.tensor([1.0, 0.0], device=self.device), op="max")
        raise NonFiniteError(f"step {self.step}: {reason}; training stopped")

    def _loss_where(self) -> str:
        """``loss 'dgs' (plugin gpnerf_plugins.losses.plugin 0.1.0)``: the loss set, from the run record."""
        return self._where("loss")

    def _where(self, kind: str) -> str:
        """``model 'gnt' (plugin gpnerf_plugins.families.plugin 0.1.0)``: a component of the run, from its record."""
        used = self.record.components.get(kind) or {}
        component = self.loss if kind == "loss" else self.model
        name = used.get("name", type(component).__name__)
        return f"{kind} {name!r} (plugin {used.get('provider', 'unknown')} {used.get('version', 'unknown')})"

    def _non_finite_inputs(self, batch: StepBatch, output: StepOutput) -> str:
        """Which of the model's outputs the loss set read were not finite (looked at only once a term is): the model's
        fault, not the loss set's, when any is."""
        fields = []
        for view, out in zip(batch.views, output.views):
            inputs = loss_inputs(view, out, self.ignore_index)
            if isinstance(inputs, ImageLossInputs):
                named = {f"image.{f}": getattr(inputs.output, f) for f in (
                    "rgb", "depth", "alpha", "scores", "semantic", "teacher_map", "logits", "features")}
            else:
                named = {"logits": inputs.logits, "teacher_at_rays": inputs.teacher_at_rays}
                for rays_name, rays in (("coarse", inputs.coarse), ("fine", inputs.fine)):
                    if isinstance(rays, RenderedRays):
                        named |= {f"{rays_name}.{f}": getattr(rays, f, None)
                                  for f in ("rgb", "depth", "semantic", "sample_semantic", "logits", "features")}
            fields += [name for name, value in named.items() if isinstance(value, Tensor) and value.is_floating_point()
                       and not all_finite(value.detach()) and name not in fields]
        if not fields:
            return "its inputs were finite: the loss set made it"
        return (f"its inputs {', '.join(fields)} from model {self.cfg.model.name!r} were not finite already: "
                "the model made it")

    # ---- the loop ----------------------------------------------------------------------------------------------

    def fit(
        self,
        until: int | None = None,
        *,
        progress: bool = True,
        loggers: Sequence[ScalarLogger] = (),
        callbacks: Sequence[TrainingCallback] = (),
    ) -> TrainResult:
        """Train to step ``until`` (``train.steps`` when None), checkpointing every ``train.checkpoint_every`` steps
        and at the end.

        Args:
            callbacks: the command's ``TrainingCallback`` s, the same protocol as the family's: timed ones run at their
                phase after the family's; those with ``timed=False`` (``evaluate_at``: an evaluation) after the step and
                its checkpoint, off the training clock, with the model back in training mode after them.

        A callback may end the loop early (``request_stop``, ``TrainingState.request_stop``): after the step it was
        asked at (that step logged), the final checkpoint is written at that step and ``TrainResult.stopped`` says why.

        Raises:
            TrainingInterrupted: on SIGINT/SIGTERM, after a checkpoint at the current step.
        """
        cfg = self.cfg.train
        total_steps = int(cfg.steps) if until is None else min(int(until), int(cfg.steps))
        bar = self._progress_bar(int(cfg.steps)) if progress and self.dist.is_main else None
        self.model.train()
        rays_done = 0
        self._clock = _Clock()
        untimed = [c for c in callbacks if not c.timed]
        self._stop_reason = None
        family = self.callbacks
        self.callbacks = {phase: [*family[phase], *(c for c in callbacks if c.timed and c.phase is phase)]
                          for phase in TrainingPhase}
        try:
            with StopRequest() as stop:
                while self.step < total_steps:
                    terms, rays, stop_signal = self.train_step(stop)
                    self.loss_names = [name for name in terms if name != "loss"]
                    self.step += 1
                    rays_done += rays
                    run_seconds = self._run_seconds()
                    if self.step % int(cfg.log_every) == 0 or self.step == total_steps:
                        self._log(terms, rays_done, run_seconds, self.elapsed + run_seconds, loggers)
                    if bar is not None:
                        bar.update(1)
                        if self.history and self.history[-1]["step"] == self.step:
                            bar.set_postfix(loss=f"{self.history[-1]['loss']:.4f}", refresh=False)
                    if stop_signal is not None:
                        path = self._checkpoint(self.training_seconds)
                        raise TrainingInterrupted(stop_signal, self.step, path)
                    if cfg.checkpoint_every and self.step % int(cfg.checkpoint_every) == 0 and self.step < total_steps:
                        self._checkpoint(self.training_seconds)
                    if untimed:
                        self._run_callbacks(untimed, stop)
                    if self._stop_agreed(agree=bool(callbacks)):
                        if not self.history or self.history[-1]["step"] != self.step:
                            self._log(terms, rays_done, run_seconds, self.elapsed + run_seconds, loggers)
                        break
        finally:
            self.callbacks = family
            if bar is not None:
                bar.close()
        seconds = self._run_seconds()
        self._clock = None
        self.elapsed += seconds
        checkpoint = self._checkpoint(self.elapsed)
        global_rays = float(self.dist.all_reduce(torch.tensor(float(rays_done), device=self.device)))
        return TrainResult(
            steps=self.step,
            seconds=self.elapsed,
            rays_per_second=global_rays / seconds if seconds > 0 else 0.0,
            world_size=self.dist.world_size,
            targets_per_rank=self.sampler.targets_per_rank,
            rays_per_step=self.rays_per_view() * int(cfg.targets_per_step),
            history=self.history,
            checkpoint=checkpoint,
            stopped=self._stop_reason,
        )

    def request_stop(self, reason: str) -> None:
        """Ask ``fit`` to end after the current step (``reason``: one line, ``TrainResult.stopped``); the first
        reason asked is kept."""
        if self._stop_reason is None:
            self._stop_reason = str(reason)

    def _stop_agreed(self, agree: bool) -> bool:
        """Whether the loop ends after this step: a stop was asked here, or (``agree``: the command gave callbacks,
        which may ask on one process alone, as a seconds budget) on any process."""
        asked = self._stop_reason is not None
        if not (agree and self.dist.enabled):
            return asked
        anywhere = float(self.dist.all_reduce(torch.tensor(float(asked), device=self.device), op="max")) > 0
        if anywhere and not asked:
            self._stop_reason = "another process asked to stop"
        return anywhere

    def rays_per_view(self) -> int:
        """``train.rays``, or a whole-image batch's pixels (the first training scene's image size)."""
        if not self.whole_images:
            return int(self.cfg.train.rays)
        scene = self.frames.scene(self.sampler.scene_names[0])
        return int(scene.height) * int(scene.width)

    @property
    def training_seconds(self) -> float:
        """Seconds spent training so far (earlier runs of a resumed run included; callbacks' time not)."""
        return self.elapsed + (self._run_seconds() if self._clock is not None else 0.0)

    def checkpoint(self) -> Path | None:
        """Write a checkpoint at the current step now (rank 0; every process must call it); its path on rank 0."""
        return self._checkpoint(self.training_seconds)

    def _run_seconds(self) -> float:
        return self._clock.seconds()

    def _run_callbacks(self, callbacks: Sequence[TrainingCallback], stop: StopRequest) -> None:
        """Run the untimed ``callbacks`` due at the step just done, off the training clock. In a single process a stop
        signal ends them at once (an evaluation can take minutes) and the checkpoint holds the step they followed;
        with several processes they run to their end (each process would stop at a different collective), and the
        stop comes after the next step."""
        done = self.step - 1
        due = [c for c in callbacks if c.due(done)]
        if not due:
            return
        with self._clock.paused():
            state = dataclasses.replace(self._state(None, None), step=done)
            try:
                with stop.raising() if self.dist.world_size == 1 else nullcontext():
                    for callback in due:
                        callback.run(state)
            except StopNow as now:
                raise TrainingInterrupted(now.signum, self.step, self._checkpoint(self.training_seconds)) from None
        self.model.train()

    def _progress_bar(self, total_steps: int) -> Any:
        from tqdm import tqdm

        return tqdm(
            total=total_steps,
            initial=self.step,
            desc="train",
            unit="step",
            dynamic_ncols=True,
            mininterval=0.5 if sys.stderr.isatty() else 30.0,
            file=sys.stderr,
        )

    def _log(
        self, terms: dict[str, Tensor], rays_done: int, run_seconds: float, total_seconds: float,
        loggers: Sequence[ScalarLogger],
    ) -> None:
        """A history entry (values averaged over processes) and the same scalars to the loggers (rank 0)."""
        names = list(terms)
        summed = torch.stack([terms[name].to(self.device, torch.float32) for name in names] + [
            torch.tensor(float(rays_done), device=self.device)
        ])
        self.dist.all_reduce(summed)
        memory = self.dist.all_reduce(torch.tensor(peak_memory_mb(self.device), device=self.device), op="max")
        values = {name: float(summed[i]) / self.dist.world_size for i, name in enumerate(names)}
        entry = {"step": float(self.step), "seconds": total_seconds} | values
        entry["grad_norm"] = float(self.last_grad_norm)
        for group in self.optimizer.param_groups:
            entry[f"lr/{group['name']}"] = group["lr"]
        entry["rays_per_second"] = float(summed[-1]) / run_seconds if run_seconds > 0 else 0.0
        entry["peak_memory_mb"] = float(memory)
        self.history.append(entry)
        scalars = {f"train/{name}": values[name] for name in names}
        scalars |= {f"train/lr/{g['name']}": g["lr"] for g in self.optimizer.param_groups}
        scalars |= {key: entry[key.removeprefix("train/")] for key in (
            "train/rays_per_second", "train/peak_memory_mb", "train/grad_norm")}
        for logger in loggers:
            logger.log(self.step, scalars)

    @contextmanager
    def evaluation_weights(self) -> Iterator[str]:
        """Within the block the model holds the weights evaluated (the average where kept); yields which."""
        if self.average is None:
            yield "trained"
            return
        with self.average.swapped_in(self.model):
            yield "average"

    # ---- checkpoints -------------------------------------------------------------------------------------------

    def _rng_state(self) -> dict[str, Any]:
        cuda = torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None
        return {"cpu": torch.get_rng_state(), "cuda": cuda}

    def _set_rng_state(self, state: dict[str, Any]) -> None:
        torch.set_rng_state(state["cpu"])
        if self.device.type == "cuda" and state["cuda"] is not None:
            torch.cuda.set_rng_state(state["cuda"], self.device)

    def _checkpoint(self, elapsed: float) -> Path | None:
        """Write a checkpoint at the current step (rank 0; every process contributes its random state)."""
        target = checkpoint_path(self.run_dir, self.step)
        check_finite_model(self.model, str(self.cfg.model.name), f"step {self.step}: checkpoint {target.name}")
        rng_states = self.dist.all_gather_object(self._rng_state())
        if not self.dist.is_main:
            return None
        path = save_checkpoint(
            target,
            record=self.record,
            model=self.model,
            optimizer=self.optimizer,
            scheduler=self.scheduler,
            step=self.step,
            sampler=self.sampler.state_dict(),
            rng_states=rng_states,
            history=self.history,
            elapsed=elapsed,
            weight_average=self.average.state_dict() if self.average is not None else None,
            classes=self.classes,
            scenes=tuple(self.sampler.scene_names),
        )
        prune_checkpoints(self.run_dir, int(self.cfg.train.keep_checkpoints))
        return path

    def _resume(self, path: Path, read: TrainedModel | None = None) -> None:
        """Continue from the checkpoint ``path``; every refusal (another model or loss, weights or optimizer state that
        do not fit, no weight average) is raised here, in the constructor, before ``run`` claims its folder.

        ``read``: ``path`` as read already (``plan_resume``'s, handed over as ``resume_from``): not read again."""
        state = (read or load_trained(path, "train.resume")).state
        self.notes += check_resume_config(path, state["config"], self.record.config_yaml, self.cfg.train.resume_strict,
                                          checkpoint_sections(state))
        load_weights(self.model, state["model"], f"checkpoint {path}")
        if self.model.capabilities.changes_size:  # its parameters took the checkpoint's sizes: new tensors
            self.optimizer, self.scheduler = self._optimizer()
        try:
            self.optimizer.load_state_dict(state["optimizer"])
            self.scheduler.load_state_dict(state["scheduler"])
        except (ValueError, KeyError) as exc:
            raise ConfigError(f"train.resume={path}: its optimizer state does not fit this model ({exc})") from None
        problem = optimizer_problem(self.model, self.optimizer, str(self.cfg.model.name))
        if problem is not None:
            raise ConfigError(f"train.resume={path}: its optimizer state does not fit the parameters ({problem})")
        if self.average is not None:
            if state.get("weight_average") is None:
                raise ConfigError(
                    f"train.resume={path}: train.ema_decay={self.average.decay} but the checkpoint kept no weight "
                    "average (resume with train.ema_decay=0, or start a new run)"
                )
            self.average.load_state_dict(state["weight_average"], f"checkpoint {path}")
        self.sampler.load_state_dict(state["sampler"])
        self.step = int(state["step"])
        self.history = list(state["history"])
        self.elapsed = float(state["elapsed"])
        rng = state["rng"]
        if len(rng) == self.dist.world_size:
            self._set_rng_state(rng[self.dist.rank])
        else:
            torch.manual_seed(process_seed(int(self.cfg.seed) + self.step, self.dist.rank))
            self.notes.append(
                f"the checkpoint was written by {len(rng)} processes and this run has {self.dist.world_size}: "
                "target views, pixels and samples resume exactly, dropout draws do not"
            )
