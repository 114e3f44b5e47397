"""Evaluation: render whole held-out views, decode them, score them with tagged protocols.

Each view is evaluated on its own into a small ``ViewRecord`` (confusion matrices, PSNR/SSIM, depth errors, timing,
and the pictures of the first few views); the records are then summarised in view order. Under torchrun each process
evaluates every ``world_size``-th view and the records are gathered, so the metrics equal a single process's.

A scene without labels (``Scene.labelled`` False, a user's capture) is rendered and scored on colour and depth only:
every label metric of a split whose scenes all lack labels is None with ``labels/unavailable_reason``, never 0, and a
split mixing both scores labels on its labelled scenes and lists the others (``labels/unlabelled_scenes``). Classes
are the model's (``Components.classes``: a checkpoint's where the dataset has no class list).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from gpnerf_core.model.build import Components
from gpnerf_core.runtime.device import peak_memory_mb
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError, DataError, NonFiniteError
from gpnerf_core.evaluation import instances as I
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.evaluation import pictures as P
from gpnerf_core.evaluation import query_protocol as Q
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.data.frames import FrameCache, choose_sources
from gpnerf_core.features.field import image_cosine
from gpnerf_core.registry.kinds import KINDS, section
from gpnerf_core.runtime.io import atomic_save_png
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.types import Frame, Prediction, Scene, SourceViews

SourcesFor = Callable[[Scene, int], SourceViews]
TargetsFor = Callable[[Scene], list[int]]
"""``scene -> held-out frame indices`` to score (a subset of ``scene.eval_frames``; the stress suite's cases)."""
"""``(scene, target frame index) -> the source views`` the model is given for that target."""

SPLIT_LABELS = {"train": "train_heldout", "unseen": "unseen"}


@dataclass
class ViewRecord:
    """What the summary needs from one evaluated view; small and picklable (gathered across processes).

    Attributes:
        position: the view's place in its split's target list (the summary's order).
        scene, frame: which view.
        quality: ``{PSNR_CLAMPED, SSIM_GAUSSIAN11}``.
        confusion, teacher_confusion, baseline_confusion: ``[K, K]`` of the rendered prediction, of the 2D
            reference and of the majority class; None without semantics or labels (or, the baseline, without a
            majority class).
        seconds: encode + render + decode time; rays: rays rendered.
        pictures: ``{file suffix: uint8 image}`` for the first ``eval.save_images`` views, else empty.
        instances, teacher_instances: an instance head's scores on the rendered map and on the 2D reference map.
        instance_baseline: a class head's connected components scored as instances (the trivial baseline), where
            the frame has instance ids.
        labelled: the scene has labels (``Scene.labelled``); without, only ``quality`` and ``depth`` are scored.
        depth: ``{DEPTH_ABS_REL, DEPTH_RMSE}``, or None when the frame has no ground-truth depth.
    """

    position: int
    scene: str
    frame: int
    quality: dict[str, float]
    confusion: torch.Tensor | None
    teacher_confusion: torch.Tensor | None
    baseline_confusion: torch.Tensor | None
    seconds: float
    rays: int
    pictures: dict[str, np.ndarray] = field(default_factory=dict)
    instances: I.InstanceRecord | None = None
    teacher_instances: I.InstanceRecord | None = None
    instance_baseline: I.InstanceRecord | None = None
    labelled: bool = True
    depth: dict[str, float] | None = None
    references: bool = False
    """The class references (majority class, the 2D reference where the model has one) were scored on this view."""
    queries: dict[str, torch.Tensor] | None = None
    """``eval.query_protocol``: ``{feature source: [K, K] confusion}`` of the nearest-prototype labels
    (``query_protocol``); None when the protocol is off or the scene has no labels."""
    feature_cosine: float | None = None
    """:data:`metrics.FEATURE_COSINE` of this view (the rendered feature field against the provider's features of the
    real frame), or None without a feature field."""


def predicts(components: Components) -> Predicts | None:
    """What the model's semantic scores are (None: colour and depth only)."""
    output = components.model.semantic_output
    return None if output is None else output.predicts


def majority_class(components: Components, frames: FrameCache, max_frames_per_scene: int = 8) -> int | None:
    """Most frequent class over (a spread sample of) the labelled training scenes' training frames; None when no
    training scene has labels."""
    dataset = components.dataset
    labels = []
    for name in dataset.scenes("train"):
        scene = frames.scene(name)
        if not scene.labelled:
            continue
        indices = scene.train_frames
        step = max(1, len(indices) // max_frames_per_scene)
        labels += [frames.frame(scene, i).semantic for i in indices[::step]]
    if not labels:
        return None
    counts = M.class_pixel_counts(labels, components.classes.num_classes, dataset.ignore_index)
    return int(np.argmax(counts))


def _area_downsample(image: torch.Tensor, stride: int) -> torch.Tensor:
    """``[H, W, 3]`` -> ``[H / s, W / s, 3]`` by averaging s x s cells (matches rays through cell centres)."""
    if stride == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], stride)[0].permute(1, 2, 0)


def evaluate(
    cfg: Any,
    components: Components,
    frames: FrameCache,
    run_dir: Path,
    dist: Distributed,
    *,
    sources_for: SourcesFor | None = None,
    targets_for: TargetsFor | None = None,
    references: bool = True,
    pictures: bool = True,
) -> dict[str, Any]:
    """Evaluate every configured split; returns ``{"eval": {split: metrics}, ...}`` ready for metrics.json.

    Every process returns the same result; rank 0 alone writes the pictures.

    Args:
        sources_for: the source views of a target (default: ``model.num_source_views`` frames from the view
            selector); the stress suite passes its cases' views here.
        targets_for: the held-out frames of a scene to score (default: all of ``scene.eval_frames``), before the
            ``eval.max_views_per_scene`` cap; the stress suite passes its cases' target views here.
        references: also score the references (2D teacher, majority class, connected-components instances).
        pictures: write the pictures of the first ``eval.save_images`` views (False: none, as at a curve point).
    """
    for split in cfg.eval.splits:
        if split not in SPLIT_LABELS:
            raise ConfigError(f"eval.splits contains {split!r}; expected some of {', '.join(SPLIT_LABELS)}")
    components.model.to(dist.device).eval()
    dataset = components.dataset
    instance_head = predicts(components) is Predicts.INSTANCES
    semantics = predicts(components) is Predicts.CLASSES
    baseline_class = majority_class(components, frames) if semantics and references else None
    queries = Q.query_protocol(cfg, components, frames) if references else None
    results: dict[str, Any] = {}
    for split in cfg.eval.splits:
        label = SPLIT_LABELS[split]
        targets = _targets(cfg, components, frames, split, targets_for)
        if not targets:
            results[label] = {"count/images": 0, "note": f"split {split!r} has no evaluation frames"}
            continue
        mine = [
            _evaluate_view(cfg, components, frames, position, scene, index, baseline_class, sources_for, references,
                           int(cfg.eval.save_images) if pictures else 0, queries)
            for position, (scene, index) in enumerate(targets)
            if position % dist.world_size == dist.rank
        ]
        records = sorted((r for shard in dist.all_gather_object(mine) for r in shard), key=lambda r: r.position)
        memory = dist.all_reduce(torch.tensor(peak_memory_mb(dist.device), device=dist.device), op="max")
        if dist.is_main:
            _write_pictures(run_dir / "images" / label, records)
        results[label] = summarize(records, components.classes.num_classes, dataset.ignore_index, semantics,
                                   float(memory), instance_head=instance_head)
        if M.QUERY_PROTOTYPE in results[label]:
            results[label][M.QUERY_PROTOTYPE].update(prototype_frames=queries.k, seed=queries.seed)
    field = components.feature_field
    compression = field.autoencoder.reconstruction() if field is not None and field.autoencoder is not None else None
    return {
        "eval": results,
        **({"feature_compression": compression.as_metrics()} if compression is not None else {}),
        "baseline_class": None if baseline_class is None else components.classes.names[baseline_class],
        "lpips": M.lpips_vgg_status(),
        "eval_world_size": dist.world_size,
    }


def check_splits_have_frames(cfg: Any, components: Components) -> list[str]:
    """Refuse ``eval.splits`` that select no frame of the dataset at all, before anything is evaluated or written; the
    notes (one line each) for the splits that are empty while another is not.

    A split's frames are the ``eval_frames`` of its scenes (the held-out frames of the ``train`` scenes; those of the
    ``unseen`` scenes).

    Raises:
        ConfigError: ``eval.splits`` empty, or every split in it without frames (naming each split, what it has, the
            dataset and what is expected).
    """
    splits = [str(split) for split in cfg.eval.splits]
    if not splits:
        raise ConfigError(f"eval.splits=[]: nothing to evaluate; expected some of {', '.join(SPLIT_LABELS)}")
    dataset = components.dataset
    empty = {}
    for split in splits:
        scenes = dataset.scenes(split)
        frames = sum(len(dataset.load_scene(name).eval_frames) for name in scenes)
        if not frames:
            empty[split] = (f"split {split!r} has {len(scenes)} scene(s) and no evaluation frame in them" if scenes
                            else f"split {split!r} has no scene")
    where = f"dataset {cfg.dataset.name!r}" + (f" (dataset.root={cfg.dataset.root})" if cfg.dataset.get("root") else "")
    if len(empty) == len(splits):
        options = [f"dataset.{key}" for key in cfg.dataset if str(key).startswith("eval") or "unseen" in str(key)]
        named = f" ({', '.join(options)})" if options else ""
        raise ConfigError(
            f"eval.splits=[{', '.join(splits)}] select no frame of {where}: {'; '.join(empty.values())}; expected "
            "held-out frames in the training scenes (split 'train') or unseen scenes (split 'unseen'): change the "
            f"dataset's held-out frame and scene options{named} or eval.splits"
        )
    return [f"{reason} in {where}: {SPLIT_LABELS[split]} scores no image" for split, reason in empty.items()]


def _targets(
    cfg: Any, components: Components, frames: FrameCache, split: str, targets_for: TargetsFor | None = None
) -> list[tuple[Scene, int]]:
    """The split's evaluation views in a fixed order (those ``targets_for`` keeps, capped per scene by
    ``eval.max_views_per_scene``)."""
    cap = int(cfg.eval.max_views_per_scene)
    targets = []
    for name in components.dataset.scenes(split):
        scene = frames.scene(name)
        indices = list(scene.eval_frames)
        if targets_for is not None:
            kept = list(targets_for(scene))
            outside = [i for i in kept if i not in indices]
            if outside:
                raise DataError(f"scene {scene.name!r}: target frame {outside[0]} is not a held-out frame "
                                f"(expected some of {indices})")
            indices = kept
        if cap:
            indices = indices[:: max(1, len(indices) // cap)][:cap]
        targets += [(scene, index) for index in indices]
    return targets


def _evaluate_view(
    cfg: Any,
    components: Components,
    frames: FrameCache,
    position: int,
    scene: Scene,
    index: int,
    baseline_class: int | None,
    sources_for: SourcesFor | None,
    references: bool,
    save_images: int,
    queries: Q.QueryProtocol | None = None,
) -> ViewRecord:
    model, dataset = components.model, components.dataset
    num_classes, ignore = components.classes.num_classes, dataset.ignore_index
    labelled = scene.labelled
    target = frames.frame(scene, index)
    if sources_for is not None:
        sources = sources_for(scene, index)
    elif model.capabilities.generalizable:
        sources = frames.source_views(
            scene, choose_sources(components.view_selector, scene, index, cfg.model.num_source_views, None)
        )
    else:
        sources = None
    camera = frames.camera(scene, target)
    segments_image = model.capabilities.segments_image
    if segments_image:  # a 2D model segments the real held-out image: the one place it is given one
        camera = dataclasses.replace(camera, image=target.rgb.to(frames.device))
    started = time.perf_counter()
    where = f"scene {scene.name!r} frame {index}"
    try:
        prediction = model.predict(
            camera,
            sources,
            stride=int(cfg.eval.render_stride),
            chunk_rays=int(cfg.eval.chunk_rays),
        )
    except NonFiniteError as exc:  # a component's output check (registry.guards) names the component, not the view
        raise NonFiniteError(f"{where}: {exc}; nothing was scored") from None
    prediction.check_finite(model.hooks.output_owners(component_names(cfg)), where)
    feature_cosine = None
    if prediction.features is not None and components.feature_field is not None:
        image = target.rgb.permute(2, 0, 1)[None].to(frames.device)
        provided = components.feature_field.maps(scene.name, [index], image)
        feature_cosine = image_cosine(prediction.features, provided[0])
    instance_head = predicts(components) is Predicts.INSTANCES
    classes = None
    if prediction.logits is not None and not instance_head:
        classes = prediction.logits.argmax(dim=1)[0].cpu()
    seconds = time.perf_counter() - started
    gt_rgb = _area_downsample(target.rgb, prediction.stride)
    rendered_rgb = prediction.rgb.cpu()
    if segments_image:  # renders no colour or depth: nothing to score (null in metrics.json, never a number)
        quality, depth = {M.PSNR_CLAMPED: math.nan, M.SSIM_GAUSSIAN11: math.nan}, None
    else:
        quality = {M.PSNR_CLAMPED: M.psnr(rendered_rgb, gt_rgb), M.SSIM_GAUSSIAN11: M.ssim(rendered_rgb, gt_rgb)}
        depth = M.depth_errors(prediction.depth.cpu(), target.depth)
    confusion = teacher_confusion = baseline_confusion = None
    instances = teacher_instances = instance_baseline = None
    instance_picture = None
    if classes is not None and labelled:
        confusion = M.confusion_matrix(classes, target.semantic, num_classes, ignore)
    scored_references = classes is not None and references and labelled
    if scored_references:
        teacher = model.teacher_logits(target.rgb.permute(2, 0, 1).to(frames.device))
        if teacher is not None:
            teacher_confusion = M.confusion_matrix(teacher.argmax(dim=1)[0].cpu(), target.semantic, num_classes, ignore)
        if baseline_class is not None:
            constant = torch.full_like(target.semantic, int(baseline_class))
            baseline_confusion = M.confusion_matrix(constant, target.semantic, num_classes, ignore)
        if target.instance is not None:
            top = torch.softmax(prediction.logits[0].float(), dim=0).max(dim=0).values.cpu()
            instance_baseline, _ = I.instance_record(*I.connected_component_instances(classes, top), target.instance)
    if instance_head and labelled:
        if target.instance is None:
            raise DataError(f"scene {scene.name!r} frame {index}: no instance ids to evaluate the instance head on")
        activation = model.semantic_output.slot_activation
        slots, confidence = I.slot_predictions(prediction.logits[0].cpu(), activation)
        instances, pairing = I.instance_record(slots, confidence, target.instance)
        instance_picture = (slots, pairing)
        teacher = model.teacher_logits(target.rgb.permute(2, 0, 1).to(frames.device)) if references else None
        if teacher is not None:
            teacher_instances, _ = I.instance_record(*I.slot_predictions(teacher[0].cpu()), target.instance)
    query_confusions = queries.confusions(scene, index, target, prediction) if queries is not None and labelled \
        else None
    pictures = {}
    if position < save_images:
        pictures = _pictures(target, prediction, classes, gt_rgb, num_classes, ignore, scene.near, scene.far,
                             labelled=labelled)
        if instance_picture is not None:
            pictures["instances"] = _instance_picture(*instance_picture, target.instance)
        elif instance_head:  # a scene without labels: the predicted instances alone
            slots, _ = I.slot_predictions(prediction.logits[0].cpu(), model.semantic_output.slot_activation)
            pictures["instances"] = vis.side_by_side([vis.colorize_instances(slots)],
                                                     ["predicted instances (no labels)"])
    return ViewRecord(
        position=position,
        scene=scene.name,
        frame=index,
        quality=quality,
        confusion=confusion,
        teacher_confusion=teacher_confusion,
        baseline_confusion=baseline_confusion,
        seconds=seconds,
        rays=int(prediction.rgb.shape[0] * prediction.rgb.shape[1]),
        pictures=pictures,
        instances=instances,
        teacher_instances=teacher_instances,
        instance_baseline=instance_baseline,
        labelled=labelled,
        depth=depth,
        references=scored_references,
        queries=query_confusions,
        feature_cosine=feature_cosine,
    )


def summarize(
    records: list[ViewRecord],
    num_classes: int,
    ignore_index: int,
    semantics: bool,
    peak_memory: float,
    *,
    instance_head: bool = False,
) -> dict[str, Any]:
    """The split's metrics from its view records, taken in order.

    Args:
        semantics: a class head (segmentation protocols); instance_head: an instance head (instance protocols).
    """
    quality = M.ImageQualityAccumulator()
    depth = M.DepthAccumulator()
    # Without a class head there are no class ids to accumulate (a dataset without a class list may have none).
    rendered, teacher, baseline = (
        (M.SegmentationAccumulator(num_classes, ignore_index) for _ in range(3)) if semantics else (None, None, None)
    )
    instances, teacher_instances, instance_baseline = (I.InstanceAccumulator() for _ in range(3))
    for record in records:
        quality.add_scores(record.quality, group=record.scene)
        if record.depth is not None:
            depth.add_scores(record.depth, group=record.scene)
        for accumulator, value in (
            (instances, record.instances),
            (teacher_instances, record.teacher_instances),
            (instance_baseline, record.instance_baseline),
        ):
            if value is not None:
                accumulator.add(value, group=record.scene)
        if record.confusion is not None:
            rendered.add_confusion(record.confusion, group=record.scene)
        if record.teacher_confusion is not None:
            teacher.add_confusion(record.teacher_confusion, group=record.scene)
        if record.baseline_confusion is not None:
            baseline.add_confusion(record.baseline_confusion, group=record.scene)
    result: dict[str, Any] = dict(quality.compute())
    result.update(depth.compute())
    fidelity = M.FeatureAccumulator()
    for record in records:
        if record.feature_cosine is not None:
            fidelity.add(record.feature_cosine, group=record.scene)
    result.update(fidelity.compute())
    unlabelled = list(dict.fromkeys(r.scene for r in records if not r.labelled))
    if not any(r.labelled for r in records):
        if semantics or instance_head:
            result.update(_labels_unavailable(M.no_labels_reason(unlabelled), instance_head))
        return _with_timing(result, records, peak_memory)
    if semantics:
        result.update(rendered.compute())
        result["per_scene"] = rendered.compute_per_group()
        if any(r.references or r.teacher_confusion is not None or r.baseline_confusion is not None for r in records):
            if any(r.baseline_confusion is not None for r in records):
                result["baseline_majority"] = baseline.compute()
            else:
                result["baseline_majority"] = None
                result[M.BASELINE_MAJORITY_UNAVAILABLE_REASON] = (
                    "no training scene has labels to take the majority class from"
                )
            if any(r.teacher_confusion is not None for r in records):
                result["teacher_2d"] = teacher.compute()
    if any(r.instances is not None for r in records):
        result.update(instances.compute())
        if any(r.teacher_instances is not None for r in records):
            result["teacher_2d"] = teacher_instances.compute()
    if any(r.instance_baseline is not None for r in records):
        result["baseline_connected_components"] = instance_baseline.compute()
    if any(r.queries for r in records):
        result[M.QUERY_PROTOTYPE] = Q.summarize_queries(records, num_classes, ignore_index)
    if unlabelled and (semantics or instance_head):
        result[M.LABELS_UNLABELLED_SCENES] = unlabelled
        result[M.COUNT_IMAGES_WITHOUT_LABELS] = sum(1 for r in records if not r.labelled)
    return _with_timing(result, records, peak_memory)


def _labels_unavailable(reason: str, instance_head: bool) -> dict[str, Any]:
    """Every label metric of a split without labels as None (never 0), with the reason."""
    keys = I.AP_KEYS if instance_head else M.SEGMENTATION_KEYS
    references = ("teacher_2d",) if instance_head else ("baseline_majority", "teacher_2d")
    return {**{key: None for key in keys}, **{name: None for name in references}, M.LABELS_UNAVAILABLE_REASON: reason}


def _with_timing(result: dict[str, Any], records: list[ViewRecord], peak_memory: float) -> dict[str, Any]:
    """``result`` with the split's ``timing``: seconds per frame, rays per second, peak memory."""
    seconds = sum(r.seconds for r in records)
    rays = sum(r.rays for r in records)
    result["timing"] = {
        "seconds_per_frame": round(seconds / len(records), 4),
        "rays_per_second": round(rays / seconds, 1) if seconds > 0 else None,
        "peak_memory_mb": round(peak_memory, 1),
    }
    return result


def _pictures(
    target: Frame,
    prediction: Prediction,
    classes: torch.Tensor | None,
    gt_rgb: torch.Tensor,
    num_classes: int,
    ignore: int,
    near: float,
    far: float,
    *,
    labelled: bool = True,
) -> dict[str, np.ndarray]:
    """The pictures of one view, by file suffix: each predicted layer (``pictures.prediction_layers``, the rendered grid
    at the image's size) beside the ground truth and the errors. Without labels the semantic picture shows the
    predicted classes alone."""
    s = prediction.stride
    layers = P.prediction_layers(prediction, near, far, None, num_classes, full_size=True)
    pictures = {
        "rgb": vis.side_by_side(
            [layers["rgb"], P.upscale(P.rgb_picture(gt_rgb), s),
             P.upscale(vis.rgb_error_map(prediction.rgb.cpu().clamp(0, 1), gt_rgb), s)],
            ["rendered RGB", "ground truth", "|error|"],
        ),
        "depth": vis.side_by_side([layers["depth"], P.depth_picture(target.depth, near, far)],
                                  ["rendered depth", "ground truth"]),
    }
    if classes is not None and labelled:
        pictures["semantic"] = vis.side_by_side(
            [vis.colorize_labels(classes, num_classes, ignore),
             vis.colorize_labels(target.semantic, num_classes, ignore),
             vis.error_map(classes, target.semantic, ignore)],
            ["predicted classes", "ground truth", "errors"],
        )
    elif classes is not None:
        pictures["semantic"] = vis.side_by_side([vis.colorize_labels(classes, num_classes)],
                                                ["predicted classes (no labels)"])
    if "features" in layers:
        pictures["features_pca"] = layers["features"]
    return pictures


def _instance_picture(slots: torch.Tensor, pairing: dict[int, int], gt: torch.Tensor) -> np.ndarray:
    """Predicted instances (each slot in the colour of the GT instance it was matched to), GT, and the pixels whose
    slot is not matched to their GT instance."""
    unmatched_base = int(gt.max()) + 1
    lookup = torch.tensor([pairing.get(k, unmatched_base + k) for k in range(int(slots.max()) + 1)])
    shown = lookup[slots]
    return vis.side_by_side(
        [vis.colorize_instances(shown), vis.colorize_instances(gt), vis.error_map(shown, gt)],
        ["predicted instances", "ground truth", "errors"],
    )


def _write_pictures(folder: Path, records: list[ViewRecord]) -> None:
    for record in records:
        stem = f"{record.scene.replace('/', '_')}_{record.frame:04d}"
        for suffix, image in record.pictures.items():
            atomic_save_png(folder / f"{stem}_{suffix}.png", image)


def print_summary(metrics: dict[str, Any], run_dir: Path) -> None:
    """A few lines on stdout: what was trained, the headline numbers per split, where the run folder is."""
    lines = []
    train = metrics.get("train")
    if train:
        lines.append(
            f"trained {train['steps']} steps in {train['seconds']:.0f} s ({train['rays_per_second']:.0f} rays/s"
            + (f", {train['world_size']} processes)" if train.get("world_size", 1) > 1 else ")")
        )
    for split, values in metrics.get("eval", {}).items():
        parts = [f"{split:>14}:"]
        if values.get("count/images") == 0:
            lines.append(f"{split:>14}: no images ({values.get('note', 'no evaluation frames')})")
            continue
        reason = values.get(M.LABELS_UNAVAILABLE_REASON)
        if reason is not None:
            parts.append(f"labels: not available ({reason})")
        else:
            parts += _label_parts(values)
        parts.append(f"| PSNR {_fmt(values.get(M.PSNR_CLAMPED), 2)} SSIM {_fmt(values.get(M.SSIM_GAUSSIAN11))}")
        if M.FEATURE_COSINE in values:
            parts.append(f"| feature field cosine {_fmt(values.get(M.FEATURE_COSINE))}")
        timing = values.get("timing", {})
        parts.append(f"| {timing.get('seconds_per_frame', float('nan')):.2f} s/frame")
        lines.append(" ".join(parts))
    lines.append(f"run folder: {run_dir.resolve()}")
    print("\n".join(lines))
    sys.stdout.flush()


def _label_parts(values: dict[str, Any]) -> list[str]:
    """The summary's label numbers of one split (mIoU and its references, or the instance APs)."""
    parts = []
    if M.MIOU_IMAGE_MEAN_PRESENT in values:
        parts.append(f"mIoU {_fmt(values.get(M.MIOU_IMAGE_MEAN_PRESENT))} (per image)")
        parts.append(f"{_fmt(values.get(M.MIOU_DATASET))} (dataset)")
        base = values.get("baseline_majority") or {}
        parts.append(f"| majority baseline {_fmt(base.get(M.MIOU_IMAGE_MEAN_PRESENT))}")
        parts.append(f"| acc {_fmt(values.get(M.ACC_TOTAL))}")
    if I.AP_MATCHED_75 in values:
        parts.append(f"AP@0.75 {_fmt(values.get(I.AP_MATCHED_75))} (matched)")
        parts.append(f"| COCO AP {_fmt(values.get(I.COCO_AP))}")
        parts.append(f"AP75 {_fmt(values.get(I.COCO_AP75))}")
    cc = values.get("baseline_connected_components")
    if cc:
        parts.append(f"| instances from connected components: AP@0.75 {_fmt(cc.get(I.AP_MATCHED_75))}")
    query = values.get(M.QUERY_PROTOTYPE)
    if query and query.get("sources"):
        scored = ", ".join(f"{name} {_fmt(v.get(M.MIOU_IMAGE_MEAN_PRESENT))}" for name, v in query["sources"].items())
        parts.append(f"| query by prototype ({query.get('prototype_frames', '?')} frame/class) mIoU: {scored}")
    unlabelled = values.get(M.LABELS_UNLABELLED_SCENES)
    if unlabelled:
        parts.append(f"(labels scored on the labelled scenes only; without labels: {', '.join(unlabelled)})")
    return parts


def _fmt(value: Any, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def component_names(cfg: Any) -> dict[str, str]:
    """The configured name of each component kind present in ``cfg`` (for messages: ``ModelFamily.output_owners``)."""
    nodes = {kind: section(cfg, kind) for kind in KINDS}
    return {kind: str(node.name) for kind, node in nodes.items() if node is not None and "name" in node}
