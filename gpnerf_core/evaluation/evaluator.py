"""Evaluation: render whole held-out views in chunks, run the head once per view, score with tagged protocols."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gpnerf_core.build import Components
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.io import atomic_save_png
from gpnerf_core.views import SceneViews, choose_sources

SPLIT_LABELS = {"train": "train_heldout", "unseen": "unseen"}


def peak_memory_mb(device: torch.device) -> float:
    """Peak resident memory of this process (CPU) or peak allocated memory (CUDA), in MiB."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def majority_class(components: Components, views: SceneViews, max_frames_per_scene: int = 8) -> int:
    """Most frequent class over (a spread sample of) the training scenes' training frames."""
    dataset = components.dataset
    labels = []
    for name in dataset.scenes("train"):
        scene = views.scene(name)
        frames = scene.train_frames
        step = max(1, len(frames) // max_frames_per_scene)
        labels += [views.frame(scene, i).semantic for i in frames[::step]]
    counts = M.class_pixel_counts(labels, dataset.num_classes, dataset.ignore_index)
    return int(np.argmax(counts))


def _area_downsample(image: torch.Tensor, stride: int) -> torch.Tensor:
    """``[H, W, 3]`` -> ``[H / s, W / s, 3]`` by averaging s x s cells (matches rays through cell centres)."""
    if stride == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], stride)[0].permute(1, 2, 0)


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def evaluate(cfg: Any, components: Components, views: SceneViews, device: torch.device, run_dir: Path) -> dict[str, Any]:
    """Evaluate every configured split; returns ``{"eval": {split: metrics}}`` ready for metrics.json."""
    model = components.model.to(device).eval()
    dataset = components.dataset
    eval_cfg = cfg.eval
    semantics = model.has_semantics
    baseline_class = majority_class(components, views) if semantics else None
    results: dict[str, Any] = {}
    for split in eval_cfg.splits:
        if split not in SPLIT_LABELS:
            raise ConfigError(f"eval.splits contains {split!r}; expected some of {', '.join(SPLIT_LABELS)}")
        results[SPLIT_LABELS[split]] = _evaluate_split(
            cfg, components, views, device, run_dir / "images" / SPLIT_LABELS[split], split, baseline_class
        )
    return {
        "eval": results,
        "baseline_class": None if baseline_class is None else dataset.class_names[baseline_class],
        "lpips": M.lpips_vgg_status(),
    }


def _evaluate_split(
    cfg: Any,
    components: Components,
    views: SceneViews,
    device: torch.device,
    image_dir: Path,
    split: str,
    baseline_class: int | None,
) -> dict[str, Any]:
    model, dataset = components.model, components.dataset
    eval_cfg = cfg.eval
    semantics = model.has_semantics
    num_classes, ignore = dataset.num_classes, dataset.ignore_index
    rendered_seg = M.SegmentationAccumulator(num_classes, ignore)
    teacher_seg = M.SegmentationAccumulator(num_classes, ignore)
    quality = M.ImageQualityAccumulator()
    baseline_targets: list[tuple[torch.Tensor, str]] = []
    rays_rendered, render_seconds, frames_done, saved = 0, 0.0, 0, 0
    targets = []
    for name in dataset.scenes(split):
        scene = views.scene(name)
        frames = list(scene.eval_frames)
        if eval_cfg.max_views_per_scene:
            step = max(1, len(frames) // int(eval_cfg.max_views_per_scene))
            frames = frames[::step][: int(eval_cfg.max_views_per_scene)]
        targets += [(scene, index) for index in frames]
    if not targets:
        return {"count/images": 0, "note": f"split {split!r} has no evaluation frames"}
    for scene, index in targets:
        target = views.frame(scene, index)
        height, width = target.height, target.width
        source_indices = choose_sources(components.view_selector, scene, index, cfg.model.num_source_views, None)
        sources = views.source_views(scene, source_indices)
        started = time.perf_counter()
        with torch.inference_mode():
            features = model.encode(sources.rgb)
            stride = int(eval_cfg.render_stride) or _semantic_stride(features, height)
            rendered = model.render_image(
                intrinsics=target.intrinsics.to(device),
                c2w=target.c2w.to(device),
                height=height,
                width=width,
                near=scene.near,
                far=scene.far,
                sources=sources,
                features=features,
                stride=stride,
                chunk_rays=int(eval_cfg.chunk_rays),
            )
            prediction = teacher_prediction = None
            if semantics and rendered.semantic is not None:
                logits = model.decode(rendered.semantic[None], (height, width)).logits
                prediction = logits.argmax(dim=1)[0].cpu()
        render_seconds += time.perf_counter() - started
        rays_rendered += rendered.rgb.shape[0] * rendered.rgb.shape[1]
        frames_done += 1
        gt_rgb = _area_downsample(target.rgb, stride)
        quality.update(rendered.rgb.cpu(), gt_rgb, group=scene.name)
        if prediction is not None:
            rendered_seg.update(prediction, target.semantic, group=scene.name)
            baseline_targets.append((target.semantic, scene.name))
            with torch.inference_mode():
                teacher_map = model.encode(target.rgb.permute(2, 0, 1)[None].to(device)).semantic
                teacher_prediction = model.decode(teacher_map, (height, width)).logits.argmax(dim=1)[0].cpu()
            teacher_seg.update(teacher_prediction, target.semantic, group=scene.name)
        if saved < int(eval_cfg.save_images):
            _save_pictures(image_dir / f"{scene.name.replace('/', '_')}_{index:04d}", target, rendered, prediction,
                           gt_rgb, num_classes, ignore, scene.near, scene.far)
            saved += 1
    result: dict[str, Any] = {}
    result.update(quality.compute())
    if semantics:
        result.update(rendered_seg.compute())
        result["per_scene"] = rendered_seg.compute_per_group()
        result["baseline_majority"] = M.constant_prediction_metrics(baseline_targets, baseline_class, num_classes, ignore)
        result["teacher_2d"] = teacher_seg.compute()
    result["timing"] = {
        "seconds_per_frame": round(render_seconds / frames_done, 4),
        "rays_per_second": round(rays_rendered / render_seconds, 1) if render_seconds > 0 else None,
        "peak_memory_mb": round(peak_memory_mb(device), 1),
    }
    return result


def _semantic_stride(features: Any, height: int) -> int:
    if features.semantic is None:
        return 1
    return max(1, height // int(features.semantic.shape[-2]))


def _save_pictures(
    prefix: Path,
    target: Any,
    rendered: Any,
    prediction: torch.Tensor | None,
    gt_rgb: torch.Tensor,
    num_classes: int,
    ignore: int,
    near: float,
    far: float,
) -> None:
    pred_rgb = rendered.rgb.cpu()
    s = rendered.stride  # rendered maps are shown at full size, one block per rendered cell
    atomic_save_png(prefix.with_name(prefix.name + "_rgb.png"), vis.side_by_side(
        [_upscale(_to_uint8(pred_rgb), s), _upscale(_to_uint8(gt_rgb), s),
         _upscale(vis.rgb_error_map(pred_rgb.clamp(0, 1), gt_rgb), s)],
        ["rendered RGB", "ground truth", "|error|"],
    ))
    atomic_save_png(prefix.with_name(prefix.name + "_depth.png"), vis.side_by_side(
        [_upscale(vis.depth_to_color(rendered.depth.cpu(), near, far), s), vis.depth_to_color(target.depth, near, far)],
        ["rendered depth", "ground truth"],
    ))
    if prediction is not None:
        atomic_save_png(prefix.with_name(prefix.name + "_semantic.png"), vis.side_by_side(
            [vis.colorize_labels(prediction, num_classes, ignore),
             vis.colorize_labels(target.semantic, num_classes, ignore),
             vis.error_map(prediction, target.semantic, ignore)],
            ["predicted classes", "ground truth", "errors"],
        ))
    if rendered.semantic is not None:
        atomic_save_png(
            prefix.with_name(prefix.name + "_features_pca.png"), _upscale(vis.pca_rgb(rendered.semantic.cpu()), s)
        )


def _upscale(image: np.ndarray, factor: int) -> np.ndarray:
    return image.repeat(factor, axis=0).repeat(factor, axis=1)


def print_summary(metrics: dict[str, Any], run_dir: Path) -> None:
    """A few lines on stdout: what was trained, the headline numbers per split, where the run folder is."""
    lines = []
    train = metrics.get("train")
    if train:
        lines.append(f"trained {train['steps']} steps in {train['seconds']:.0f} s ({train['rays_per_second']:.0f} rays/s)")
    for split, values in metrics.get("eval", {}).items():
        parts = [f"{split:>14}:"]
        if M.MIOU_IMAGE_MEAN_PRESENT in values:
            parts.append(f"mIoU {_fmt(values.get(M.MIOU_IMAGE_MEAN_PRESENT))} (per image)")
            parts.append(f"{_fmt(values.get(M.MIOU_DATASET))} (dataset)")
            base = values.get("baseline_majority", {})
            parts.append(f"| majority baseline {_fmt(base.get(M.MIOU_IMAGE_MEAN_PRESENT))}")
            parts.append(f"| acc {_fmt(values.get(M.ACC_TOTAL))}")
        parts.append(f"| PSNR {_fmt(values.get(M.PSNR_CLAMPED), 2)} SSIM {_fmt(values.get(M.SSIM_GAUSSIAN11))}")
        timing = values.get("timing", {})
        parts.append(f"| {timing.get('seconds_per_frame', float('nan')):.2f} s/frame")
        lines.append(" ".join(parts))
    lines.append(f"run folder: {run_dir.resolve()}")
    print("\n".join(lines))
    sys.stdout.flush()


def _fmt(value: Any, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"
