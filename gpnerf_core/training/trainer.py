"""The training loop: one target view per step, coarse + fine rendering, fused-map head, weighted loss terms."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from gpnerf_core.build import Components
from gpnerf_core.errors import ConfigError, NonFiniteError
from gpnerf_core.fusion import cells_of_pixels, fuse_rendered, gather_cells
from gpnerf_core.geometry import rays_through_pixels
from gpnerf_core.training.checkpoint import load_checkpoint, save_checkpoint
from gpnerf_core.types import FeatureMaps, LossInputs
from gpnerf_core.views import SceneViews, choose_sources


@dataclass
class TrainResult:
    steps: int
    seconds: float
    rays_per_second: float
    history: list[dict[str, float]] = field(default_factory=list)
    checkpoint: Path | None = None


def make_optimizer(model: torch.nn.Module, lrs: Any) -> torch.optim.Optimizer:
    """Adam with one parameter group per module kind and its own learning rate."""
    groups = []
    for name, params in model.parameter_groups().items():
        params = [p for p in params if p.requires_grad]
        if params:
            groups.append({"params": params, "lr": float(getattr(lrs, name)), "name": name})
    return torch.optim.Adam(groups)


def exponential_decay(rate: float, steps: int) -> Callable[[int], float]:
    if steps <= 0 or not 0 < rate <= 1:
        raise ConfigError(f"train.lr_decay_rate must be in (0, 1] and lr_decay_steps > 0, got {rate} and {steps}")
    return lambda step: rate ** (step / steps)


class Trainer:
    """Trains ``components.model`` with ``components.loss`` on the dataset's training scenes."""

    def __init__(self, cfg: Any, components: Components, device: torch.device, run_dir: Path, config_yaml: str) -> None:
        if components.loss is None:
            raise ConfigError("training needs a loss set: add +loss=<name> (e.g. +loss=dgs)")
        self.cfg = cfg
        self.components = components
        self.model = components.model.to(device)
        self.loss = components.loss.to(device)
        self.device = device
        self.run_dir = run_dir
        self.config_yaml = config_yaml
        self.views = SceneViews(components.dataset, device)
        self.scene_names = list(components.dataset.scenes("train"))
        if not self.scene_names:
            raise ConfigError(f"dataset {cfg.dataset.name!r} has no training scenes")
        self.generator = torch.Generator().manual_seed(int(cfg.seed))
        self.optimizer = make_optimizer(self.model, cfg.train.lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, exponential_decay(cfg.train.lr_decay_rate, cfg.train.lr_decay_steps)
        )
        self.step = 0
        self.history: list[dict[str, float]] = []
        self.elapsed = 0.0

    def _randint(self, high: int) -> int:
        return int(torch.randint(high, (1,), generator=self.generator))

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        model, loss_set = self.model, self.loss
        scene = self.views.scene(self.scene_names[self._randint(len(self.scene_names))])
        target_index = scene.train_frames[self._randint(len(scene.train_frames))]
        source_indices = choose_sources(
            self.components.view_selector, scene, target_index, cfg.model.num_source_views, self.generator
        )
        sources = self.views.source_views(scene, source_indices)
        target = self.views.frame(scene, target_index)
        height, width = target.height, target.width
        num_views = sources.num_views

        semantics = loss_set.needs_semantics
        images = sources.rgb
        if semantics:
            images = torch.cat([images, target.rgb.permute(2, 0, 1)[None].to(self.device)])
        maps = model.encode(images)
        source_maps = FeatureMaps(
            radiance=maps.radiance[:num_views],
            semantic=maps.semantic[:num_views] if maps.semantic is not None else None,
        )

        num_rays = min(int(cfg.train.rays), height * width)
        flat = torch.randperm(height * width, generator=self.generator)[:num_rays]
        pixels = torch.stack([flat % width, flat // width], dim=-1).to(torch.float32).to(self.device)
        rays = rays_through_pixels(
            pixels, target.intrinsics.to(self.device), target.c2w.to(self.device), scene.near, scene.far
        )
        coarse, fine = model.render_rays(
            rays,
            sources,
            source_maps,
            randomized=True,
            with_semantic=semantics,
            with_sample_semantic=loss_set.needs_sample_semantics,
            generator=self.generator,
        )
        rows = pixels[:, 1].long(), pixels[:, 0].long()
        logits = labels = teacher_at_rays = None
        if semantics:
            teacher = maps.semantic[num_views:]
            cells = cells_of_pixels(pixels, (height, width), tuple(teacher.shape[-2:]))
            teacher_at_rays = gather_cells(teacher, cells)
            last = fine if fine is not None else coarse
            head_input = fuse_rendered(teacher, last.semantic, cells) if cfg.train.fuse_rendered else teacher
            logits = model.decode(head_input, (height, width)).logits
            labels = target.semantic[None].to(self.device)
        inputs = LossInputs(
            coarse=coarse,
            fine=fine,
            target_rgb=target.rgb.to(self.device)[rows],
            target_depth=target.depth.to(self.device)[rows],
            logits=logits,
            labels=labels,
            teacher_at_rays=teacher_at_rays,
            ignore_index=self.components.dataset.ignore_index,
        )
        terms = loss_set(inputs)
        for name, value in terms.items():
            if not torch.isfinite(value).all():
                raise NonFiniteError(
                    f"step {self.step}: loss term {name!r} is {value.item()} "
                    f"(scene {scene.name!r}, target frame {target_index}); training stopped"
                )
        total: Tensor = sum(terms.values())
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(
            self.model.parameters(), cfg.train.grad_clip if cfg.train.grad_clip > 0 else math.inf
        )
        if not torch.isfinite(grad_norm):
            raise NonFiniteError(f"step {self.step}: gradient norm is {grad_norm.item()}; training stopped")
        self.optimizer.step()
        self.scheduler.step()
        return {name: float(value.detach()) for name, value in terms.items()} | {"loss": float(total.detach())}

    def fit(self, progress: bool = True) -> TrainResult:
        cfg = self.cfg.train
        if cfg.resume:
            self._resume(Path(cfg.resume))
        total_steps = int(cfg.steps)
        bar = None
        if progress:
            from tqdm import tqdm

            interactive = sys.stderr.isatty()
            bar = tqdm(
                total=total_steps,
                initial=self.step,
                desc="train",
                unit="step",
                dynamic_ncols=True,
                mininterval=0.5 if interactive else 30.0,
                file=sys.stderr,
            )
        self.model.train()
        rays_done = 0
        started = time.perf_counter()
        while self.step < total_steps:
            values = self.train_step()
            self.step += 1
            rays_done += int(cfg.rays)
            now = time.perf_counter()
            if self.step % int(cfg.log_every) == 0 or self.step == total_steps:
                entry = {"step": float(self.step), "seconds": self.elapsed + now - started} | values
                entry["lr_feature_extractor"] = self.optimizer.param_groups[0]["lr"]
                self.history.append(entry)
            if bar is not None:
                bar.update(1)
                rate = rays_done / (now - started)
                bar.set_postfix(loss=f"{values['loss']:.4f}", rays_s=f"{rate:.0f}", refresh=False)
            if cfg.checkpoint_every and self.step % int(cfg.checkpoint_every) == 0 and self.step < total_steps:
                self._checkpoint(self.elapsed + now - started)
        if bar is not None:
            bar.close()
        seconds = time.perf_counter() - started
        self.elapsed += seconds
        checkpoint = self._checkpoint(self.elapsed)
        return TrainResult(
            steps=self.step,
            seconds=self.elapsed,
            rays_per_second=rays_done / seconds if seconds > 0 else 0.0,
            history=self.history,
            checkpoint=checkpoint,
        )

    def _checkpoint(self, elapsed: float) -> Path:
        path = self.run_dir / "checkpoints" / f"step_{self.step:07d}.pt"
        save_checkpoint(
            path,
            model=self.model,
            optimizer=self.optimizer,
            scheduler=self.scheduler,
            step=self.step,
            generator=self.generator,
            history=self.history,
            elapsed=elapsed,
            config_yaml=self.config_yaml,
        )
        return path

    def _resume(self, path: Path) -> None:
        state = load_checkpoint(path, self.model, optimizer=self.optimizer, scheduler=self.scheduler)
        self.step = state["step"]
        self.generator.set_state(state["generator"])
        self.history = list(state["history"])
        self.elapsed = float(state["elapsed"])
