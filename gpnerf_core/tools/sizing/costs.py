"""What a configuration costs before it is trained: parameters and floating-point operations per rendered ray."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from gpnerf_core.interfaces.model import parameter_counts
from torch.utils.flop_counter import FlopCounterMode

from gpnerf_core.tools.bench.measure import view_renderer
from gpnerf_core.engine.setup import setup_process
from gpnerf_core.model.build import build_components
from gpnerf_core.data.frames import FrameCache


@dataclass(frozen=True)
class StaticCost:
    """Attributes: parameters (all model tensors); flops_per_ray: matmul and convolution FLOPs of rendering one
    held-out view (source encoding included) divided by its rays (torch's FLOP counter); rays: rays of that view;
    flops_counted: False for a family rasterizing Gaussians (numba kernels the counter cannot see: ``flops_per_ray``
    is then only its torch part, shown as n/a). A per-scene family's parameters are replaced by its trained count once
    a trial has trained (before, it holds no Gaussians)."""

    parameters: int
    flops_per_ray: float
    rays: int
    flops_counted: bool = True

    def flops_text(self) -> str:
        """MFLOP per ray with two decimals, or ``n/a`` where the counter cannot see the rendering."""
        return f"{self.flops_per_ray / 1e6:.2f}" if self.flops_counted else "n/a"


def static_cost(cfg: Any, scene_name: str) -> StaticCost:
    """Build the model ``cfg`` describes (randomly initialised: the counts do not depend on the weights; a per-scene
    model initialised on ``scene_name`` as training starts it) and render the first held-out view of ``scene_name``
    once under the FLOP counter, on the CPU."""
    setup_process(cfg)
    components = build_components(cfg)
    model = components.model.eval()
    frames = FrameCache(components.dataset, torch.device("cpu"))
    if not model.capabilities.generalizable:  # fitted on its scene: started as training starts it (hooks.initialise)
        model.hooks.initialise(frames.scene(scene_name))
    render = view_renderer(cfg, model, frames, components.view_selector, scene_name)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        prediction = render()
    flops = int(counter.get_total_flops())
    rays = int(prediction.rgb.shape[0] * prediction.rgb.shape[1])
    return StaticCost(parameters=int(parameter_counts(model)["total"]), flops_per_ray=flops / rays, rays=rays,
                      flops_counted=not model.capabilities.gaussians)
