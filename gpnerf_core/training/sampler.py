"""Which target views, source views and pixels each training step uses, on every process."""

from __future__ import annotations

from typing import Any, Sequence

import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.data.frames import FrameCache, choose_sources
from gpnerf_core.interfaces import ViewSelector
from gpnerf_core.types import StepBatch, TargetView

SEED_RANGE = 2**62
"""Per-view seeds are drawn from [0, SEED_RANGE)."""


def check_global_batch(targets_per_step: int, world_size: int) -> None:
    """Every process trains on the same number of target views: the world size must divide the global batch."""
    if targets_per_step < 1:
        raise ConfigError(f"train.targets_per_step={targets_per_step}: expected a positive number of target views")
    if targets_per_step % world_size:
        raise ConfigError(
            f"train.targets_per_step={targets_per_step} is not divisible by the world size {world_size}: "
            "every process trains on the same number of target views; choose a multiple of the process count"
        )


class StepSampler:
    """Draws the global batch of target views of every step and hands this process its share.

    The global batch is drawn from one selection generator, seeded with ``seed`` and advanced identically on
    every process, so a step's targets do not depend on the world size; process ``rank`` keeps targets
    ``[rank * k, (rank + 1) * k)`` with ``k = targets_per_step / world_size``. Each target then gets its own
    seed, from which its source views, its pixels and its rendering noise are drawn, so a target trains the
    same whichever process handles it: N processes x k targets equal 1 process x N k targets.

    Args:
        frames: the frame cache; the batch goes to its device.
        selector: the source-view selector.
        scene_names: the training scenes.
        num_source_views: V, source views per target; 0 for a per-scene model (``TargetView.sources`` None).
        rays_per_view: pixels drawn per target view (at most the image's pixel count).
        whole_images: draw no pixels: each target view is rendered whole (``TargetView.whole_image``, the batch of a
            family that trains on whole images); ``rays_per_view`` is then unused.
        targets_per_step: the global batch of target views per step.
        seed: seed of the selection generator.
        rank, world_size: this process and the number of processes; ``world_size`` must divide
            ``targets_per_step``.
    """

    def __init__(
        self,
        frames: FrameCache,
        selector: ViewSelector,
        *,
        scene_names: Sequence[str],
        num_source_views: int,
        rays_per_view: int,
        targets_per_step: int,
        seed: int,
        rank: int = 0,
        world_size: int = 1,
        whole_images: bool = False,
    ) -> None:
        if not scene_names:
            raise ConfigError("the dataset has no training scenes")
        check_global_batch(targets_per_step, world_size)
        self.frames = frames
        self.selector = selector
        self.scene_names = list(scene_names)
        self.num_source_views = num_source_views
        self.rays_per_view = rays_per_view
        self.whole_images = whole_images
        self.targets_per_step = targets_per_step
        self.rank = rank
        self.targets_per_rank = targets_per_step // world_size
        self.generator = torch.Generator().manual_seed(seed)

    def next_batch(self) -> StepBatch:
        """This process's target views of the next step."""
        slots = [self._draw_slot() for _ in range(self.targets_per_step)]
        first = self.rank * self.targets_per_rank
        mine = slots[first : first + self.targets_per_rank]
        return StepBatch(tuple(self._target_view(*slot) for slot in mine))

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])

    def _randint(self, generator: torch.Generator, high: int) -> int:
        return int(torch.randint(high, (1,), generator=generator, device="cpu"))

    def _draw_slot(self) -> tuple[str, int, int]:
        """(scene, target frame, view seed) of one slot of the global batch."""
        scene = self.frames.scene(self.scene_names[self._randint(self.generator, len(self.scene_names))])
        frame = scene.train_frames[self._randint(self.generator, len(scene.train_frames))]
        return scene.name, frame, self._randint(self.generator, SEED_RANGE)

    def _target_view(self, scene_name: str, frame_index: int, seed: int) -> TargetView:
        view_generator = torch.Generator().manual_seed(seed)
        frames = self.frames
        scene = frames.scene(scene_name)
        sources = None
        if self.num_source_views:
            indices = choose_sources(self.selector, scene, frame_index, self.num_source_views, view_generator)
            sources = frames.source_views(scene, indices)
        frame = frames.frame(scene, frame_index)
        height, width = frame.height, frame.width
        pixels = None  # a whole image: no pixels drawn; a masked frame's excluded pixels are marked (``valid``)
        if not self.whole_images:
            if frame.valid is None:
                flat = torch.randperm(height * width, generator=view_generator, device="cpu")
            else:  # a masked frame: rays only through the pixels its mask keeps
                kept = frame.valid.reshape(-1).nonzero().squeeze(1).cpu()
                flat = kept[torch.randperm(kept.numel(), generator=view_generator, device="cpu")]
            flat = flat[: min(self.rays_per_view, flat.numel())]
            pixels = torch.stack([flat % width, flat // width], dim=-1).to(torch.float32)
        device = frames.device
        return TargetView(
            scene=scene.name,
            frame=frame_index,
            camera=frames.camera(scene, frame),
            image=frame.rgb.permute(2, 0, 1).to(device),
            depth=frame.depth.to(device),
            labels=frame.semantic.to(device),
            sources=sources,
            pixels=pixels.to(device) if pixels is not None else None,
            render_seed=self._randint(view_generator, SEED_RANGE),
            instances=None if frame.instance is None else frame.instance.to(device),
            whole_image=self.whole_images,
            valid=frame.valid.to(device) if self.whole_images and frame.valid is not None else None,
        )
