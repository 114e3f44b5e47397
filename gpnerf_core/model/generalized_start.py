"""A per-scene Gaussian family started from what a generalizable model predicts for the scene (issue 54).

``predict_start`` turns a generalizable checkpoint's answer for a scene's training frames into Gaussians in the world
frame (``GaussianStart``), two ways by the model's capabilities:

- **a feed-forward Gaussian family** (``Capabilities.gaussians``: ``mvsplat``, ``mvsplat_unet``): each chosen training
  frame with its nearest other training frames as one source set; of the Gaussians predicted, the frame's own pixels'
  (view-major, the frame first), those with opacity above ``OPACITY_FLOOR`` (AnySplat's post-optimisation start drops
  opacity <= 0.01), with their positions, scales, rotations, opacities, world harmonics and features as predicted;
- **a ray family** (GP-NeRF, the other generalizable NeRFs): each chosen training frame rendered from the other training
  frames as ``export`` renders (``predict`` at stride 0), each cell back-projected and kept where ``export``'s
  multi-view agreement and depth bounds keep it (MVSGaussian's start fuses depth with a reprojection check), one
  isotropic Gaussian per kept cell (``cell_gaussians``).

Views overlap, so Gaussians of several views describe one surface: they are merged on a voxel grid about the median
Gaussian's footprint, keeping the most opaque Gaussian of each voxel (a kept Gaussian stays one coherent Gaussian, not
an average of several), then cut to the ``budget`` most opaque (``most_opaque``, said once).

``points_start`` keeps the scene's own points instead (its structure from motion or depth, where a per-scene family
starts without a checkpoint) and takes only their semantics from the model: each point's features read where it falls
in the frames the model predicted (``point_features``), for a model whose labels hold where its depth does not.

``begin_from_start`` then gives a per-scene ``GaussianFamily`` its Gaussians and decoder from a start; the family's
``GaussianHooks.initialise`` calls it when ``family.start`` is set (``GaussianFamily.use_start``). ``start_overrides``
are the Hydra overrides that size the per-scene family's config to carry the start.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.geometry.gaussians.harmonics import colour_to_dc
from gpnerf_core.geometry.gaussians.initialisation import neighbour_scales, scene_extent
from gpnerf_core.geometry.gaussians.parameters import rows_from_gaussians
from gpnerf_core.geometry.gaussians.scene import GaussianScene
from gpnerf_core.geometry.point_fusion import (
    DepthView,
    agreeing_views,
    backproject,
    cell_scores,
    conflicting_views,
    inside_bounds,
    nearest_cells,
    rendered_view,
)
from gpnerf_core.geometry.rays import pixel_grid
from gpnerf_core.types import Scene, ScenePoints

if TYPE_CHECKING:
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.interfaces import ViewSelector

OPACITY_FLOOR = 0.01
"""A feed-forward Gaussian at or below this opacity is dropped (AnySplat's ``simple_trainer.py``: ``<= 0.01``)."""
START_OPACITY = 0.8
"""A ray family's cell Gaussians' opacity (``predict_start``'s default ``opacity``). The hand-off wants the started
model to render what the generalizable model rendered at step 0: a cell's Gaussian at 0.8, plus its neighbours' overlap
(``CELL_SCALE``), hides what is behind the surface as the rendered depth says it should (3DGS's 0.1 lets the
background through until training raises it, a drop at the hand-off), while below 1 the opacity keeps a gradient
(the sigmoid's slope at 0.8 is 0.16, at 0.99 0.01) and a floater that training should remove can still fade."""
CELL_SCALE = 0.5
"""A cell Gaussian's standard deviation in cell footprints (``depth x stride / focal``, metres). Gaussians of one
standard deviation sigma on a grid of spacing 2 sigma sum to a surface flat within about 1.5 % (the sum's first
Fourier term is ``exp(-2 pi^2 sigma^2 / spacing^2)`` = 0.007 of its mean), so neighbouring cells overlap without holes
or stripes, while each cell's colour and feature spread about one cell, the rendered map's own resolution, not
more (no blur beyond what was predicted)."""
MIN_VIEWS = 1
"""Other views that must render a surface at a cell's depth for its Gaussian to stay (``export.min_views``'s
default)."""
TOLERANCE = 0.1
"""Relative depth tolerance of that agreement and of seeing through (``export.tolerance`` is 0.05: a start keeps more
of a surface whose predicted depth errs, and the per-scene fit corrects it)."""
MAX_CONFLICTS = 3
"""Other views that may see through a Gaussian (their rendered surface behind it) before it is dropped as a floater:
predicted depth errs by a few per cent in every view (GP-NeRF's median error on the unseen layout is about 0.25 m), so
a surface seen by thirty views is seen through by a few of them; at 0 too much of it goes (holes), above 5 the
floaters stay (measured on the unseen layout's held-out frames, docs/fit.md)."""
SPARSE_START = 0.1
"""A start that keeps under this share of the Gaussians predicted says why (``fusion_note``)."""
MERGED_OPACITY_LIMIT = 0.99
"""Most opacity a merged Gaussian takes from its voxel's coverage (below 1: its sigmoid keeps a gradient)."""
GEOMETRIES = ("predicted", "points")
"""``fit.start_geometry``: the model's predicted geometry (``predict_start``) or the scene's own points with the
model's semantics (``points_start``)."""
SEMANTICS = ("features", "scores", "none")
"""``GaussianStart.semantics``: features a head decodes, K class scores, or nothing."""


@dataclass(frozen=True)
class GaussianStart:
    """What a generalizable model predicts for a scene, as the start of a per-scene Gaussian family.

    Attributes:
        gaussians: G Gaussians in the world frame; ``features`` ``[G, C]`` (semantic features), ``[G, K]`` (class
            scores) or None (``semantics`` "none").
        semantics: "features" (a head decodes them: ``head_state`` holds its weights), "scores" (K class scores) or
            "none".
        head_state: the generalizable model's head's ``state_dict`` ("features"), else None.
        head_config: that head's config (the checkpoint's ``head`` group, ``{"name": ..., ...}``), or None.
        feature_levels: equal channel blocks of a feature, finest first (the extractor's ``semantic_levels``; 1 for
            scores).
        feature_stride: pixels per cell of the map the head decoded in the generalizable model (1 for scores).
        classes: the generalizable model's class names (empty when unknown).
        family: the generalizable model's family (``model.name``).
        frames: the training frames whose predictions were used.
        predicted: Gaussians before merging (after the opacity floor or the agreement).
        extent: the scene's extent (``scene_extent``, metres), what a per-scene family's ``gaussians.extent`` holds.
        notes: what the start says once (the budget's cut).
        geometry: where the Gaussians stand: "predicted" (the model's depth or Gaussians, ``predict_start``) or
            "points" (the scene's own points, the model giving their semantics: ``points_start``).
    """

    gaussians: GaussianScene
    semantics: str
    head_state: dict[str, Tensor] | None
    feature_levels: int
    feature_stride: int
    classes: tuple[str, ...]
    family: str
    frames: tuple[int, ...]
    predicted: int
    extent: float = 1.0
    head_config: dict[str, Any] | None = None
    notes: tuple[str, ...] = ()
    geometry: str = "predicted"

    @property
    def feature_dim(self) -> int:
        """C (or K): the width of each Gaussian's features, 0 without."""
        features = self.gaussians.features
        return 0 if features is None else int(features.shape[1])


# ---- predicting ------------------------------------------------------------------------------------------------------


def predict_start(model: Any, frames: "FrameCache", selector: "ViewSelector", scene: Scene, *, num_source_views: int,
                  budget: int, every: int = 1, opacity: float = START_OPACITY, min_views: int = MIN_VIEWS,
                  tolerance: float = TOLERANCE, max_conflicts: int = MAX_CONFLICTS, chunk_rays: int = 4096,
                  family: str | None = None, budget_key: str = "model.max_gaussians",
                  classes: tuple[str, ...] = (), head_config: Mapping[str, Any] | None = None) -> GaussianStart:
    """The start a generalizable ``model`` predicts for ``scene`` (the module docstring).

    Args:
        model: a generalizable family in eval mode (``Capabilities.generalizable``).
        frames, selector: the dataset's frames and the run's view selector (the source views).
        num_source_views: source views per prediction (``model.num_source_views``): a Gaussian family's set holds the
            frame itself and its nearest others; a ray family renders each frame from that many others.
        budget: most Gaussians kept (``model.max_gaussians``), >= 1; ``budget_key``: the key that set it, for the note.
        every: every ``every``-th training frame is predicted.
        opacity: a ray family's cell Gaussians' opacity in (0, 1) (``START_OPACITY``).
        min_views, tolerance, max_conflicts: the depth-map fusion that keeps a frame's Gaussians (``consistent``).
        chunk_rays: rays a ray family renders at once.
        family: the model's family name for messages and the start (default: its module's package).
        classes: the model's class names (the checkpoint's dataset classes).
        head_config: the checkpoint's ``head`` config when the model has a head.
    """
    name = family or family_of(model)
    caps = model.capabilities
    if not caps.generalizable:
        raise ConfigError(f"model={name} is a per-scene family: a start is predicted by a generalizable model "
                          "(a feed-forward Gaussian family such as mvsplat, or a ray family such as gnt); expected a "
                          "checkpoint of one")
    _check_options(budget, every, opacity, num_source_views)
    chosen = tuple(scene.train_frames[::every])
    if min_views > len(chosen) - 1:
        raise ConfigError(f"min_views={min_views}: only {len(chosen)} training frame(s) are predicted, so a Gaussian "
                          f"can agree with at most {len(chosen) - 1} other view(s); lower it or predict more frames")
    parts = frame_predictions(model, frames, selector, scene, chosen, num_source_views=num_source_views,
                              opacity=opacity, chunk_rays=chunk_rays, family=name)
    predicted = concatenate(consistent(parts, scene, min_views=min_views, tolerance=tolerance,
                                       max_conflicts=max_conflicts))
    sparse = fusion_note(parts, predicted.count, scene, min_views=min_views, tolerance=tolerance,
                         max_conflicts=max_conflicts)
    if not predicted.count:
        raise DataError(f"scene {scene.name!r}: model={name} left no Gaussian to start from in training frames "
                        f"{list(chosen)} (opacity <= {OPACITY_FLOOR}, outside the depth bounds, seen by fewer than "
                        f"{min_views} other view(s) or seen through by more than {max_conflicts} within {tolerance:g});"
                        " expected a checkpoint fitted to such scenes, or looser fit.start_* options")
    merged = voxel_keep_opaque(predicted, median_footprint(predicted))
    kept, note = most_opaque(merged, budget, budget_key)
    semantics, head_state, levels, stride = _semantics(model, predicted, frames, scene)
    return GaussianStart(gaussians=kept, semantics=semantics, head_state=head_state, feature_levels=levels,
                         feature_stride=stride, classes=tuple(classes), family=name, frames=chosen,
                         predicted=predicted.count, extent=scene_extent(scene),
                         head_config=dict(head_config) if head_config is not None and semantics == "features" else None,
                         notes=tuple(n for n in (sparse, note) if n))


def points_start(model: Any, frames: "FrameCache", selector: "ViewSelector", scene: Scene, points: ScenePoints, *,
                 num_source_views: int, opacity: float, every: int = 1, tolerance: float = TOLERANCE,
                 chunk_rays: int = 4096, family: str | None = None, classes: tuple[str, ...] = (),
                 head_config: Mapping[str, Any] | None = None, origin: str = "points") -> GaussianStart:
    """The scene's own ``points`` (its structure-from-motion points or depth, ``starting_points``: the geometry a
    per-scene family starts from without a checkpoint) with the semantics a generalizable ``model`` predicts for them
    (``fit.start_geometry=points``).

    Each point is a Gaussian as 3DGS starts one (its colour, the scale of its three nearest neighbours, no rotation,
    opacity ``opacity``: the family's ``model.init_opacity``); its features are the model's, read where the point
    falls in every ``every``-th training frame as ``predict_start`` renders or predicts it (``point_features``). Where
    the model's depth errs (a capture) its labels still hold: the geometry comes from the scene, the classes from the
    model. The start then renders what a start from points renders, not what the model rendered (no hand-off of its
    image); the decoder begins from the model's head. ``origin`` names where the points came from, for the note.
    """
    name = family or family_of(model)
    if not model.capabilities.generalizable:
        raise ConfigError(f"model={name} is a per-scene family: a start is predicted by a generalizable model; "
                          "expected a checkpoint of one")
    _check_options(max(points.count, 1), every, opacity, num_source_views)
    if not points.count:
        raise DataError(f"scene {scene.name!r} gave no points to start from ({origin})")
    chosen = tuple(scene.train_frames[::every])
    parts = frame_predictions(model, frames, selector, scene, chosen, num_source_views=num_source_views,
                              opacity=START_OPACITY, chunk_rays=chunk_rays, family=name)
    gaussians = points_as_gaussians(points, opacity, point_features(points.xyz.float(), parts, tolerance))
    semantics, head_state, levels, stride = _semantics(model, gaussians, frames, scene)
    return GaussianStart(gaussians=gaussians, semantics=semantics, head_state=head_state, feature_levels=levels,
                         feature_stride=stride, classes=tuple(classes), family=name, frames=chosen,
                         predicted=points.count, extent=scene_extent(scene),
                         head_config=dict(head_config) if head_config is not None and semantics == "features" else None,
                         geometry="points")


def frame_predictions(model: Any, frames: "FrameCache", selector: "ViewSelector", scene: Scene,
                      chosen: tuple[int, ...], *, num_source_views: int, opacity: float, chunk_rays: int, family: str
                      ) -> list[tuple[GaussianScene, DepthView]]:
    """Per chosen training frame, the model's Gaussians of its pixels or cells (row-major, every one) and the depth
    they stand on: a feed-forward Gaussian family's own (``frame_gaussians``), a ray family's rendered cells
    (``ray_gaussians``)."""
    if model.capabilities.gaussians:
        return [frame_gaussians(model, frames, selector, scene, index, num_source_views) for index in chosen]
    return [ray_gaussians(model, frames, selector, scene, index, num_source_views=num_source_views, opacity=opacity,
                          chunk_rays=chunk_rays, family=family) for index in chosen]


def point_features(xyz: Tensor, parts: list[tuple[GaussianScene, DepthView]], tolerance: float) -> Tensor | None:
    """``[P, C]`` each point's feature from the frames' predictions (``frame_predictions``; None when they carry
    none): the mean of the features of its nearest cell over the frames that see it (inside the image and not behind
    the frame's predicted surface by more than ``tolerance``, relative); over the frames it falls inside where none
    sees it (predicted depth that errs short hides it everywhere); the mean of every cell where it falls in none."""
    if not parts or any(gaussians.features is None for gaussians, _ in parts):
        return None
    count, width = xyz.shape[0], int(parts[0][0].features.shape[1])
    seen, seen_count = torch.zeros(count, width), torch.zeros(count)
    inside_sum, inside_count = torch.zeros(count, width), torch.zeros(count)
    for gaussians, view in parts:
        inside, depth, cell = nearest_cells(xyz, view)
        features = gaussians.features.float()[cell]
        visible = inside & (depth <= (1.0 + tolerance) * view.depth.reshape(-1)[cell])
        seen += features * visible[:, None]
        seen_count += visible
        inside_sum += features * inside[:, None]
        inside_count += inside
    overall = torch.cat([gaussians.features.float() for gaussians, _ in parts]).mean(dim=0)
    features = overall.expand(count, width).clone()
    some = inside_count > 0
    features[some] = inside_sum[some] / inside_count[some, None]
    visible = seen_count > 0
    features[visible] = seen[visible] / seen_count[visible, None]
    return features


def points_as_gaussians(points: ScenePoints, opacity: float, features: Tensor | None) -> GaussianScene:
    """3DGS's start from ``points`` (``parameters.rows_from_points``) as Gaussians: centres, colours as the degree-0
    harmonic, isotropic scales of the three nearest neighbours (``neighbour_scales``, metres), no rotation, every
    opacity ``opacity``; ``features`` ``[P, C]`` or None."""
    count = points.count
    rotations = torch.zeros(count, 4)
    rotations[:, 0] = 1.0
    xyz = points.xyz.float()
    return GaussianScene(means=xyz, scales=neighbour_scales(xyz)[:, None].repeat(1, 3), rotations=rotations,
                         opacities=torch.full((count,), float(opacity)),
                         harmonics=colour_to_dc(points.rgb.float().clamp(0, 1))[..., None],
                         labels=torch.full((count,), -1, dtype=torch.long), features=features)


def family_of(model: Any) -> str:
    """A model's family name: its ``name`` when it declares one, else its module's package
    (``gpnerf_plugins.families.mvsplat.model`` -> ``mvsplat``)."""
    declared = getattr(type(model), "name", None)
    if isinstance(declared, str):
        return declared
    parts = type(model).__module__.split(".")
    return parts[-2] if len(parts) > 1 else type(model).__name__


def _check_options(budget: int, every: int, opacity: float, views: int) -> None:
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 1:
        raise ConfigError(f"model.max_gaussians={budget!r}: expected an integer >= 1 (the start's Gaussian budget)")
    if every < 1:
        raise ConfigError(f"every={every!r}: expected an integer >= 1 (every n-th training frame starts Gaussians)")
    if not 0.0 < opacity < 1.0:
        raise ConfigError(f"opacity={opacity!r}: expected a starting opacity in (0, 1)")
    if views < 1:
        raise ConfigError(f"model.num_source_views={views!r}: expected an integer >= 1")


def _semantics(model: Any, predicted: GaussianScene, frames: "FrameCache", scene: Scene
               ) -> tuple[str, dict[str, Tensor] | None, int, int]:
    """``(semantics, head_state, feature_levels, feature_stride)`` of what the model's Gaussians carry."""
    if predicted.features is None:
        return "none", None, 1, 1
    head = getattr(model, "head", None)
    if head is None:
        return "scores", None, 1, 1
    state = {key: value.detach().clone() for key, value in head.state_dict().items()}
    return "features", state, int(getattr(head, "in_levels", 1)), _head_stride(model, frames, scene)


def _head_stride(model: Any, frames: "FrameCache", scene: Scene) -> int:
    """Pixels per cell of the semantic map the model's head decodes (its extractor's semantic map of a frame)."""
    frame = frames.frame(scene, scene.train_frames[0])
    with torch.no_grad():
        maps = model.extractor(frame.rgb.permute(2, 0, 1)[None].to(frames.device))
    return scene.height // int(maps.semantic.shape[-2])


def frame_gaussians(model: Any, frames: "FrameCache", selector: "ViewSelector", scene: Scene, index: int,
                    num_views: int) -> tuple[GaussianScene, DepthView]:
    """A feed-forward Gaussian family's Gaussians of frame ``index``'s own pixels (one per pixel, row-major), predicted
    from the frame and its ``num_views - 1`` nearest other training frames, and the frame's depth they make (their
    centres' camera z on the full pixel grid), on the CPU."""
    from gpnerf_core.data.frames import sources_at_pose

    others = sources_at_pose(selector, scene, scene.c2w[index], num_views - 1, index) if num_views > 1 else []
    indices = [index, *[i for i in others if i != index]]
    sources = frames.source_views(scene, indices)
    encode = getattr(model, "encode_sources", None)
    with torch.no_grad():
        if encode is not None:  # the source set encoded once: scene_gaussians then skips the labels a start ignores
            gaussians = model.scene_gaussians(None, near=scene.near, far=scene.far,
                                              features=encode(sources, near=scene.near, far=scene.far))
        else:
            gaussians = model.scene_gaussians(sources, near=scene.near, far=scene.far)
    per_view = gaussians.count // len(indices)
    if per_view != scene.height * scene.width or per_view * len(indices) != gaussians.count:
        raise DataError(f"scene {scene.name!r} frame {index}: the model predicted {gaussians.count} Gaussians for "
                        f"{len(indices)} source views of {scene.height}x{scene.width}, expected one per pixel of "
                        "each (view-major, row-major)")
    own = _on_cpu(gaussians.subset(torch.arange(per_view, device=gaussians.means.device)))
    c2w = scene.c2w[index].float().cpu()
    depth = ((own.means - c2w[:3, 3]) @ c2w[:3, :3])[:, 2].reshape(scene.height, scene.width)
    view = DepthView(depth=depth, pixels=pixel_grid(scene.height, scene.width, 1),
                     intrinsics=scene.intrinsics[index].float().cpu(), c2w=c2w, height=scene.height, width=scene.width)
    return own, view


def ray_gaussians(model: Any, frames: "FrameCache", selector: "ViewSelector", scene: Scene, index: int, *,
                  num_source_views: int, opacity: float, chunk_rays: int, family: str
                  ) -> tuple[GaussianScene, DepthView]:
    """A ray family's cell Gaussians of frame ``index`` rendered from the other training frames as ``export`` renders
    it (``cell_gaussians``), and the rendered depth they stand on."""
    from gpnerf_core.model.view_inputs import view_inputs

    frame = frames.frame(scene, index)
    camera = frames.camera(scene, frame)
    given = view_inputs(model, frames, selector, scene, camera.c2w, num_source_views, exclude=index)
    with torch.no_grad():
        prediction = model.predict(camera, given.sources, stride=0, chunk_rays=chunk_rays, features=given.features)
    if prediction.depth is None:
        raise ConfigError(f"model={family} predicts no Gaussians and renders no depth: a start needs one of them")
    view = rendered_view(prediction, camera)  # export's rendered_points, without the labels a start ignores
    return cell_gaussians(prediction, camera, backproject(view), opacity, head=getattr(model, "head", None)), view


def consistent(parts: list[tuple[GaussianScene, DepthView]], scene: Scene, *, min_views: int, tolerance: float,
               max_conflicts: int) -> list[GaussianScene]:
    """Each frame's Gaussians kept where depth-map fusion keeps a point: inside the scene's depth bounds, opacity above
    ``OPACITY_FLOOR``, seen at the same depth (``tolerance``, relative) by at least ``min_views`` other frames
    (``agreeing_views``: MVSGaussian's reprojection check), and in front of the surface of at most ``max_conflicts``
    other frames (``conflicting_views``: a Gaussian another view sees through is a floater; predicted depth errs, and
    one floater in front of a surface hides it from every view behind)."""
    views = [view for _, view in parts]
    agreeing = agreeing_views(views, tolerance) if min_views > 0 else [None] * len(views)
    conflicts = conflicting_views(views, tolerance)
    kept = []
    for (gaussians, view), agree, conflict in zip(parts, agreeing, conflicts):
        keep = inside_bounds(view.depth.reshape(-1), scene) & (gaussians.opacities > OPACITY_FLOOR)
        keep &= conflict <= max_conflicts
        if agree is not None:
            keep &= agree >= min_views
        kept.append(gaussians.subset(keep))
    return kept


def fusion_note(parts: list[tuple[GaussianScene, DepthView]], kept: int, scene: Scene, *, min_views: int,
                tolerance: float, max_conflicts: int) -> str | None:
    """A note when the fusion keeps under ``SPARSE_START`` of the predicted Gaussians, with how many each rule
    dropped (a model whose depth fails on the data: every pixel at a depth bound, or views that disagree)."""
    total = sum(gaussians.count for gaussians, _ in parts)
    if not total or kept >= SPARSE_START * total:
        return None
    views = [view for _, view in parts]
    at_bounds = sum(int((~inside_bounds(view.depth.reshape(-1), scene)).sum()) for view in views)
    seen_through = sum(int((count > max_conflicts).sum()) for count in conflicting_views(views, tolerance))
    alone = sum(int((count < min_views).sum()) for count in agreeing_views(views, tolerance)) if min_views else 0
    return (f"the start keeps {kept} of the {total} Gaussians predicted in scene {scene.name!r}'s training frames: "
            f"{at_bounds} at a depth bound (near {scene.near:g}, far {scene.far:g}: the model's depth failed there), "
            f"{seen_through} seen through by more than {max_conflicts} other frame(s) (fit.start_conflicts), {alone} "
            f"agreed by fewer than {min_views} (fit.start_min_views), within {tolerance:g} (fit.start_tolerance)")


def cell_gaussians(prediction: Any, camera: Any, xyz: Tensor, opacity: float, *, head: Any) -> GaussianScene:
    """One Gaussian per rendered cell of ``prediction`` (row-major, as ``export.rendered_points``): centre ``xyz``
    ``[N, 3]`` (``backproject``), the rendered colour (clamped to [0, 1]) as the degree-0 harmonic, isotropic standard
    deviation ``CELL_SCALE x depth x stride / focal`` (metres), no rotation, opacity ``opacity``; features the cell's
    rendered semantic feature (a model with a head) or its mean class scores (``cell_scores``), None without
    either."""
    rgb = prediction.rgb.detach().float().cpu().clamp(0, 1).reshape(-1, 3)
    depth = prediction.depth.detach().float().cpu().reshape(-1)
    focal = 0.5 * float(camera.intrinsics[0, 0] + camera.intrinsics[1, 1])
    sigma = (CELL_SCALE * depth.clamp_min(0) * prediction.stride / focal).clamp_min(1e-6)
    count = xyz.shape[0]
    features = None
    if head is not None and prediction.semantic is not None:
        if tuple(prediction.semantic.shape[1:]) != tuple(prediction.depth.shape):
            raise DataError(f"the rendered semantic map is {list(prediction.semantic.shape)} for a depth grid of "
                            f"{list(prediction.depth.shape)}: a start needs one feature per rendered cell (stride 0)")
        features = prediction.semantic.detach().float().cpu().flatten(1).T  # [h w, C]
    elif prediction.logits is not None:
        features = cell_scores(prediction).flatten(1).T  # [h w, K]
    rotations = torch.zeros(count, 4)
    rotations[:, 0] = 1.0
    return GaussianScene(means=xyz.float(), scales=sigma[:, None].repeat(1, 3), rotations=rotations,
                         opacities=torch.full((count,), float(opacity)), harmonics=colour_to_dc(rgb.float())[..., None],
                         labels=torch.full((count,), -1, dtype=torch.long), features=features)


# ---- merging ---------------------------------------------------------------------------------------------------------


def _on_cpu(scene: GaussianScene) -> GaussianScene:
    def moved(value: Tensor | None) -> Tensor | None:
        return None if value is None else value.detach().float().cpu() if value.is_floating_point() else value.cpu()

    return GaussianScene(**{name: moved(getattr(scene, name)) for name in
                            ("means", "scales", "rotations", "opacities", "harmonics", "labels", "features")})


def concatenate(parts: list[GaussianScene]) -> GaussianScene:
    """The Gaussians of ``parts`` in order (features kept when every part has them)."""
    if not parts:
        raise DataError("a start needs at least one training frame; the scene gave none")
    features = None
    if all(part.features is not None for part in parts):
        features = torch.cat([part.features for part in parts])
    return GaussianScene(**{name: torch.cat([getattr(part, name) for part in parts]) for name in
                            ("means", "scales", "rotations", "opacities", "harmonics", "labels")}, features=features)


def median_footprint(gaussians: GaussianScene) -> float:
    """The median Gaussian's footprint, metres: twice the geometric mean of its three standard deviations (a cell
    Gaussian's is its cell, ``CELL_SCALE``); 0 without Gaussians."""
    if not gaussians.count:
        return 0.0
    return float(2.0 * gaussians.scales.clamp_min(1e-12).log().mean(dim=1).exp().median())


def voxel_keep_opaque(gaussians: GaussianScene, voxel: float) -> GaussianScene:
    """The most opaque Gaussian of each ``voxel``-metre cell of a grid from the world origin (ties: the first), in their
    order, carrying the voxel's coverage as its opacity: ``1 - prod(1 - opacity)`` over the voxel's Gaussians, at most
    ``MERGED_OPACITY_LIMIT`` (views overlap: a surface element several views predicted semi-transparent, each covering
    it in part, is covered by their union; keeping one of them at its own opacity would leave holes). All of them, as
    they are, when ``voxel`` is 0. Deterministic."""
    if voxel <= 0 or gaussians.count <= 1:
        return gaussians
    keys = torch.floor(gaussians.means.double() / voxel).long()
    _, cell = torch.unique(keys, dim=0, return_inverse=True)
    cells = int(cell.max()) + 1
    best = torch.full((cells,), -1.0, dtype=gaussians.opacities.dtype).scatter_reduce(
        0, cell, gaussians.opacities, reduce="amax")
    rows = torch.arange(gaussians.count)
    top = gaussians.opacities == best[cell]
    first = torch.full((cells,), gaussians.count, dtype=torch.long).scatter_reduce(
        0, cell[top], rows[top], reduce="amin")
    transmitted = torch.zeros(cells, dtype=torch.float64).index_add_(
        0, cell, torch.log1p(-gaussians.opacities.double().clamp_max(1 - 1e-6)))
    coverage = (1 - transmitted.exp()).clamp_max(MERGED_OPACITY_LIMIT).to(gaussians.opacities.dtype)
    order = torch.argsort(first)
    kept = gaussians.subset(first[order])
    return dataclasses.replace(kept, opacities=torch.maximum(kept.opacities, coverage[order]))


def most_opaque(gaussians: GaussianScene, budget: int, key: str = "model.max_gaussians"
                ) -> tuple[GaussianScene, str | None]:
    """At most ``budget`` Gaussians: the most opaque (ties: the first), in their order, and the note said once when some
    were dropped (None when all fit)."""
    if gaussians.count <= budget:
        return gaussians, None
    order = torch.sort(-gaussians.opacities, stable=True).indices[:budget]
    note = (f"a Gaussian budget below the start's count keeps the most opaque {budget} of its {gaussians.count} "
            f"Gaussians ({key}={budget}); raise {key} to keep them all")
    return gaussians.subset(order.sort().values), note


# ---- handing over ----------------------------------------------------------------------------------------------------


def start_overrides(start: GaussianStart) -> list[str]:
    """The Hydra overrides a per-scene Gaussian family's config (``semantic_3dgs``) needs to carry ``start``:
    ``model.feature_dim`` (C or K), ``model.feature_levels``, ``model.feature_stride`` and, for "features", the
    generalizable run's head (``+head=<name>`` and its ``head.<key>=<value>``); none without semantics."""
    if start.semantics == "none":
        return []
    overrides = [f"model.feature_dim={start.feature_dim}", f"model.feature_levels={start.feature_levels}",
                 f"model.feature_stride={start.feature_stride}"]
    if start.semantics == "features":
        if not start.head_config or "name" not in start.head_config:
            raise ConfigError(f"the start from model={start.family} decodes features with a head, but its head config "
                              "is not known (predict_start's head_config: the checkpoint's head group)")
        config = dict(start.head_config)
        overrides.append(f"+head={config.pop('name')}")
        overrides.extend(f"head.{key}={_hydra_value(value)}" for key, value in _flat(config))
    return overrides


def _flat(config: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``(dotted key, value)`` of a nested config, keys sorted."""
    pairs: list[tuple[str, Any]] = []
    for key, value in sorted(config.items()):
        if isinstance(value, Mapping):
            pairs.extend(_flat(value, f"{prefix}{key}."))
        else:
            pairs.append((f"{prefix}{key}", value))
    return pairs


def _hydra_value(value: Any) -> str:
    """A config value as a Hydra override's right-hand side (lists as ``[a,b]``, None as ``null``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_hydra_value(item) for item in value) + "]"
    return str(value)


def begin_from_start(family: Any, start: GaussianStart,
                     scene_classes: tuple[str, ...] | None) -> list[str]:
    """Give ``family`` (a ``GaussianFamily``) its Gaussians and decoder from ``start``; the notes to say once.

    The Gaussian rows from the start's (``rows_from_gaussians``: the colour's degree cut or padded to the family's);
    the family's ``start_channel`` from the start's features, its other channels as ``GaussianHooks.initialise``
    starts them (``RGB2SH(U(0, 1))``); ``gaussians.extent`` the scene's; the colour's active degree the start's
    (training's schedule sets it from its first step, ``GaussianHooks.colour_degree``); the decoder begun from the start
    (``family.begin_decoder``). Where ``scene_classes`` differ from the start's classes, the geometry and colour are
    kept and the start channel and decoder start afresh, with one note naming both class lists.
    """
    gaussians = family.gaussians
    rows = rows_from_gaussians(start.gaussians, sh_degree=gaussians.sh_degree)
    notes = list(start.notes)
    same = scene_classes is None or tuple(scene_classes) == tuple(start.classes)
    if not same:
        notes.append(f"the start's classes {list(start.classes)} differ from the scene's {list(scene_classes)}: its "
                     "geometry and colour are kept, its class features and the decoder start afresh")
    channel = getattr(family, "start_channel", None)
    carried = same and channel is not None and start.semantics != "none"
    for name, width in gaussians.channels.items():
        if carried and name == channel:
            rows[name] = _start_channel(start, name, width, family)
        else:
            rows[name] = colour_to_dc(torch.rand(start.gaussians.count, width))
    gaussians.set_rows({name: value.to(gaussians.means.device, gaussians.means.dtype)
                        for name, value in rows.items()})
    gaussians.extent.fill_(start.extent)
    degree = math.isqrt(int(start.gaussians.harmonics.shape[-1])) - 1  # rendered as predicted until training's schedule
    gaussians.active_degree.fill_(min(gaussians.sh_degree, degree))
    if carried:
        family.begin_decoder(start)
    return notes


def _start_channel(start: GaussianStart, name: str, width: int, family: Any) -> Tensor:
    features = start.gaussians.features
    if features is None or int(features.shape[1]) != width:
        have = 0 if features is None else int(features.shape[1])
        raise ConfigError(f"model={family.name}: its {name} channel holds {width} values, the start from "
                          f"model={start.family} {have}; expected model.feature_dim={have} (start_overrides)")
    return features.float()

