"""The query protocol (``eval.query_protocol=true``; :data:`gpnerf_core.evaluation.metrics.QUERY_PROTOTYPE`): how well
a feature space answers queries by example, with no class head.

Per labelled scene: for every class, ``eval.prototype_frames`` (k) of the scene's training frames that show it are
drawn (a permutation of the training frames seeded by ``seed`` and the scene's name: the same frames at every run,
whatever the model); each drawn frame gives its class's pixels, nothing else. The model renders those frames at their
own cameras (a generalizable model from the other training frames), and each class's prototype is the mean of the
normalised features of its cells (``features.queries.class_prototypes``). Every held-out frame the evaluation scores
is then segmented by nearest prototype (cosine), the labels shown at the image's size (a cell's label on each of its
pixels), and scored with the segmentation protocols of a class head: per-image mIoU (the paper's), accuracy and the
dataset-level numbers, beside the closed-set head's on the same frames.

Feature sources, each where the model or the run has it:

- ``feature_field``: the rendered feature field (``Prediction.features``: a provider's features distilled);
- ``semantic_embedding``: the rendered semantic embedding a head decodes (``Prediction.semantic``);
- ``provider_2d``: the feature provider's own 2D features of the real images (prototypes from the real training
  frames, segmentation of the real held-out frames): the 2D reference the fields are distilled from.

A class none of the scene's training frames shows has no prototype: its pixels are always wrong (as a class the head
never predicts). The protocol renders ``k x classes`` frames more per scene (at most), so it is off by default.
"""

from __future__ import annotations

import dataclasses
import zlib
from typing import Any, Callable

import torch
import torch.nn.functional as F

from gpnerf_core.data.frames import FrameCache, choose_sources
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.features.queries import class_prototypes, nearest_prototype
from gpnerf_core.types import Frame, Prediction, Scene

SOURCES = ("feature_field", "semantic_embedding", "provider_2d")
"""The feature sources the protocol scores, in report order."""

ProviderFeatures = Callable[[Scene, list[int]], torch.Tensor]
"""``(scene, frame indices) -> [n, C, h, w]``: a provider's features of the real frames (``frame_features``)."""


def rendered_sources(prediction: Prediction) -> dict[str, torch.Tensor]:
    """The rendered feature maps ``[C, h, w]`` of a prediction, by source name (those it has)."""
    maps = {"feature_field": prediction.features, "semantic_embedding": prediction.semantic}
    return {name: value.detach().float() for name, value in maps.items() if value is not None}


def prototype_frames(scene: Scene, labels: dict[int, torch.Tensor], num_classes: int, k: int,
                     seed: int) -> dict[int, list[int]]:
    """The training frames each class's prototype is taken from: ``{class: [frame, ...]}`` (up to ``k`` frames that
    show the class, the first in a permutation of the training frames seeded by ``seed`` and the scene's name; a class
    no frame shows is absent).

    Args:
        labels: training frame index -> its ``[H, W]`` labels.
    """
    generator = torch.Generator().manual_seed(int(seed) * 1_000_003 + zlib.crc32(scene.name.encode()))
    order = [scene.train_frames[i] for i in torch.randperm(len(scene.train_frames), generator=generator).tolist()]
    chosen: dict[int, list[int]] = {}
    for index in order:
        shown = torch.unique(labels[index])
        for value in shown.tolist():
            if 0 <= value < num_classes and len(chosen.setdefault(value, [])) < k:
                chosen[value].append(index)
    return {c: frames for c, frames in sorted(chosen.items()) if frames}


def labels_at_image(cells: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[h, w]`` labels of a feature grid at the ``(H, W)`` image: each pixel takes the label of the cell it falls in
    (nearest; a grid that divides the image gives each cell's label to each of its pixels)."""
    if tuple(cells.shape) == tuple(size):
        return cells
    return F.interpolate(cells[None, None].float(), size=tuple(size), mode="nearest")[0, 0].long()


@dataclasses.dataclass
class QueryProtocol:
    """Prototypes per scene (taken once, at the scene's first scored frame) and the confusion of each held-out frame's
    nearest-prototype labels, per feature source.

    Args:
        render: ``(scene, frame index) -> Prediction`` of a training frame at its own camera.
        num_classes, ignore_index: the classes scored.
        k: training frames per class (``eval.prototype_frames``); seed: which ones (``seed``).
        provider_features: a provider's features of the real frames, or None (no ``provider_2d`` source).
    """

    render: Callable[[Scene, int], Prediction]
    frames: FrameCache
    num_classes: int
    ignore_index: int
    k: int = 1
    seed: int = 0
    provider_features: ProviderFeatures | None = None
    _prototypes: dict[str, dict[str, torch.Tensor]] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ConfigError(f"eval.prototype_frames={self.k!r}: expected an integer >= 1 (labelled training frames "
                              "per class)")

    def prototypes(self, scene: Scene) -> dict[str, torch.Tensor]:
        """``{source: [K, C] prototypes}`` of ``scene`` (rows of NaN for classes without one)."""
        if scene.name not in self._prototypes:
            labels = {i: self.frames.frame(scene, i).semantic for i in scene.train_frames}
            chosen = prototype_frames(scene, labels, self.num_classes, self.k, self.seed)
            per_frame: dict[int, set[int]] = {}
            for value, indices in chosen.items():
                for index in indices:
                    per_frame.setdefault(index, set()).add(value)
            maps: dict[str, list[torch.Tensor]] = {}
            kept_labels: list[torch.Tensor] = []
            indices = sorted(per_frame)
            for index in indices:
                own = labels[index]
                allowed = torch.tensor(sorted(per_frame[index]), dtype=own.dtype)
                kept_labels.append(torch.where(torch.isin(own, allowed), own, torch.full_like(own, -1)))
                for name, value in rendered_sources(self.render(scene, index)).items():
                    maps.setdefault(name, []).append(value)
            if self.provider_features is not None and indices:
                maps["provider_2d"] = list(self.provider_features(scene, indices).float())
            self._prototypes[scene.name] = {
                name: class_prototypes(values, kept_labels, self.num_classes, self.ignore_index)
                for name, values in maps.items() if len(values) == len(kept_labels) and values
            }
        return self._prototypes[scene.name]

    def confusions(self, scene: Scene, index: int, target: Frame, prediction: Prediction) -> dict[str, torch.Tensor]:
        """``{source: [K, K] confusion}`` of held-out frame ``index``'s nearest-prototype labels against its labels."""
        prototypes = self.prototypes(scene)
        maps = rendered_sources(prediction)
        if self.provider_features is not None and "provider_2d" in prototypes:
            maps["provider_2d"] = self.provider_features(scene, [index])[0].float()
        size = tuple(target.semantic.shape)
        out = {}
        for name in SOURCES:
            if name in maps and name in prototypes and bool(torch.isfinite(prototypes[name]).all(dim=1).any()):
                cells = nearest_prototype(maps[name], prototypes[name]).cpu()
                out[name] = M.confusion_matrix(labels_at_image(cells, size), target.semantic, self.num_classes,
                                               self.ignore_index)
        return out


def summarize_queries(records: list[Any], num_classes: int, ignore_index: int) -> dict[str, Any]:
    """The split's :data:`~gpnerf_core.evaluation.metrics.QUERY_PROTOTYPE` entry from its view records' ``queries``:
    ``{"sources": {source: segmentation protocols}}`` (``evaluate`` adds ``prototype_frames`` and ``seed``)."""
    accumulators: dict[str, M.SegmentationAccumulator] = {}
    for record in records:
        for name, confusion in (record.queries or {}).items():
            accumulators.setdefault(name, M.SegmentationAccumulator(num_classes, ignore_index)).add_confusion(
                confusion, group=record.scene)
    return {"sources": {name: accumulators[name].compute() for name in SOURCES if name in accumulators}}


def frame_renderer(cfg: Any, components: Any, frames: FrameCache) -> Callable[[Scene, int], Prediction]:
    """``(scene, frame index) -> Prediction`` of a frame at its own camera, as evaluation renders a held-out frame (a
    generalizable model from ``model.num_source_views`` other training frames the view selector picks; a 2D model
    given the real image)."""
    model = components.model

    def render(scene: Scene, index: int) -> Prediction:
        target = frames.frame(scene, index)
        sources = None
        if model.capabilities.generalizable:
            sources = frames.source_views(scene, choose_sources(components.view_selector, scene, index,
                                                                cfg.model.num_source_views, None))
        camera = frames.camera(scene, target)
        if model.capabilities.segments_image:
            camera = dataclasses.replace(camera, image=target.rgb.to(frames.device))
        with torch.no_grad():
            return model.predict(camera, sources, stride=int(cfg.eval.render_stride),
                                 chunk_rays=int(cfg.eval.chunk_rays))

    return render


def query_protocol(cfg: Any, components: Any, frames: FrameCache) -> QueryProtocol | None:
    """The protocol ``eval.query_protocol`` asks for, with the ``provider_2d`` source where a feature provider is
    configured (None: off, or a model without classes to score)."""
    if not bool(cfg.eval.get("query_protocol", False)) or components.classes.num_classes < 1:
        return None
    provider_features = provider_features_of(cfg, components)
    return QueryProtocol(render=frame_renderer(cfg, components, frames), frames=frames,
                         num_classes=components.classes.num_classes, ignore_index=components.dataset.ignore_index,
                         k=cfg.eval.get("prototype_frames", 1), seed=int(cfg.seed),
                         provider_features=provider_features)


def provider_features_of(cfg: Any, components: Any) -> ProviderFeatures | None:
    """A configured feature provider's features of the real frames (``+feature_provider=<name>``), read through its
    on-disk cache (``frame_features``); None without a provider."""
    from gpnerf_core.features import build_feature_provider, frame_features

    field = getattr(components, "feature_field", None)
    provider = field.provider if field is not None else build_feature_provider(cfg)
    if provider is None:
        return None
    return lambda scene, indices: frame_features(provider, components.dataset, scene, list(indices))
