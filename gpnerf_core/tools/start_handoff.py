"""What a generalized start loses at the hand-off, frame by frame (docs/fit.md, docs/results_detail.md "Generalized
start, per-scene finish").

    python -m gpnerf_core.tools.start_handoff --checkpoint <generalizable run's .pt> [--frames 3] [--opacity 0.8] \
        [--min-views 1] [--tolerance 0.1] [--conflicts 3] [dataset overrides, e.g. 'dataset.scenes=[unseen_00]']

Predicts the start of the scene (``generalized_start.predict_start`` with the given fusion options, at most 200,000
Gaussians, as ``fit checkpoint=...`` does) and, for the first ``--frames`` held-out frames, renders the start's
Gaussians (colour only) and the generalizable model's own view (``predict`` from the training frames but itself),
and prints per frame: PSNR of each against the frame, the start's accumulated opacity (coverage) and the median
absolute depth error of each against the frame's depth (where it has some). Nothing is written.
"""

from __future__ import annotations

import argparse
import sys

import torch

from gpnerf_core.data.frames import FrameCache
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.geometry.gaussians.harmonics import sh_colours
from gpnerf_core.geometry.gaussians.rasterizer import rasterize_gaussians, strided_camera
from gpnerf_core.geometry.gaussians.records import Gaussians
from gpnerf_core.model.generalized_start import predict_start
from gpnerf_core.model.trained import load_trained
from gpnerf_core.model.view_inputs import view_inputs


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    return float(-10 * torch.log10(((image.clamp(0, 1) - target) ** 2).mean()))


def depth_error(depth: torch.Tensor, target: torch.Tensor | None) -> float | None:
    if target is None or not bool((target > 0).any()):
        return None
    known = target > 0
    return float((depth[known] - target[known]).abs().median())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--opacity", type=float, default=0.8)
    parser.add_argument("--min-views", type=int, default=1)
    parser.add_argument("--tolerance", type=float, default=0.1)
    parser.add_argument("--conflicts", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args, overrides = parser.parse_known_args()
    torch.set_num_threads(args.threads)
    trained = load_trained(args.checkpoint)
    opened = open_trained(trained, overrides, command="start_handoff", other_data=True)
    model = opened.components.model.eval()
    frames = FrameCache(opened.components.dataset, opened.device)
    scene = frames.scene(opened.components.dataset.scenes("train")[0])
    views = int(opened.cfg.model.num_source_views)
    start = predict_start(model, frames, opened.components.view_selector, scene, num_source_views=views,
                          budget=200_000, opacity=args.opacity, min_views=args.min_views, tolerance=args.tolerance,
                          max_conflicts=args.conflicts, family=trained.family)
    g = start.gaussians
    print(f"start: {g.count} Gaussians ({start.predicted} fused before merging) of model {trained.family!r}, "
          f"scene {scene.name!r}; notes: {list(start.notes) or 'none'}")
    print("frame | model PSNR | start PSNR | start coverage | model depth error | start depth error")
    for index in list(scene.eval_frames)[: args.frames]:
        frame = frames.frame(scene, index)
        camera = frames.camera(scene, frame)
        given = view_inputs(model, frames, opened.components.view_selector, scene, camera.c2w, views, exclude=index)
        with torch.no_grad():
            own = model.predict(camera, given.sources, stride=1, chunk_rays=4096, features=given.features)
        intrinsics, height, width = strided_camera(camera, 1)
        colours = sh_colours(g.harmonics, g.means - camera.c2w[:3, 3].cpu())
        out = rasterize_gaussians(Gaussians(g.means, g.scales, g.rotations, g.opacities, colours),
                                  intrinsics=intrinsics.cpu(), c2w=camera.c2w.cpu(), height=height, width=width)
        rendered = out.depth / out.alpha.clamp_min(1e-6)
        target = frame.rgb.float().cpu()
        sensor = frame.depth.float().cpu() if frame.depth is not None else None
        model_error, start_error = depth_error(own.depth.cpu(), sensor), depth_error(rendered, sensor)
        print(f"{index} | {psnr(own.rgb.cpu(), target):.2f} | {psnr(out.features[..., :3], target):.2f} | "
              f"{float(out.alpha.mean()):.3f} | {model_error if model_error is None else round(model_error, 3)} | "
              f"{start_error if start_error is None else round(start_error, 3)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
