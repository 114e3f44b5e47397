"""Typed hand-offs between the stages of a generalizable NeRF.

Conventions used by every record below:

* Cameras follow OpenCV: x right, y down, z forward. Poses are camera-to-world 4x4 matrices (``c2w``),
  translation in metres.
* Pixel coordinates ``(u, v)`` are in full-resolution pixels of the image the intrinsics belong to, with
  integer values at pixel centres (so a centred principal point is ``cx = (W - 1) / 2``).
* Depth is the z-coordinate in the camera frame (not the distance along the ray), in metres; 0 = unknown.
* Shape letters: R rays, S samples per ray, V source views, C channels, H/W image height/width,
  B blocks of a transformer, K classes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.runtime.finite import all_finite


@dataclass(frozen=True)
class Frame:
    """One posed, labelled image of a scene, as a dataset returns it.

    Attributes:
        rgb: ``[H, W, 3]`` float32 in [0, 1].
        depth: ``[H, W]`` float32 metres (camera z), 0 where unknown.
        semantic: ``[H, W]`` int64 class ids in ``[0, num_classes)`` or the dataset's ``ignore_index``.
        instance: ``[H, W]`` int64 instance ids (0 = background) or None when the dataset has none.
        intrinsics: ``[3, 3]`` float32 pinhole matrix at this image's resolution.
        c2w: ``[4, 4]`` float32 camera-to-world pose (OpenCV).
        valid: ``[H, W]`` bool, False where the capture's mask excludes the pixel (never trained on; its label is the
            ignore index and its depth 0), or None when every pixel counts.
    """

    rgb: Tensor
    depth: Tensor
    semantic: Tensor
    intrinsics: Tensor
    c2w: Tensor
    instance: Tensor | None = None
    valid: Tensor | None = None

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


@dataclass(frozen=True)
class ScenePoints:
    """A scene's sparse 3D points (structure from motion), in the scene's world.

    Attributes:
        xyz: ``[P, 3]`` float32 positions, metres (the frames' world, after the dataset's scale).
        rgb: ``[P, 3]`` float32 colours in [0, 1].
    """

    xyz: Tensor
    rgb: Tensor

    def __post_init__(self) -> None:
        count = self.xyz.shape[0] if self.xyz.ndim == 2 else -1
        if tuple(self.xyz.shape) != (count, 3) or tuple(self.rgb.shape) != (count, 3):
            raise ValueError(f"ScenePoints xyz {list(self.xyz.shape)}, rgb {list(self.rgb.shape)}: expected [P, 3] each")

    @property
    def count(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class Scene:
    """A scene: its cameras and frame lists, with frames loaded on demand.

    Attributes:
        name: unique name within the dataset (``office_0/Sequence_1``, ``scene0000_00``, ...).
        c2w: ``[N, 4, 4]`` float32 poses of all N frames (OpenCV, metres).
        intrinsics: ``[N, 3, 3]`` float32, at ``height`` x ``width``.
        height, width: image size every frame of the scene is loaded at.
        near, far: depth bounds in metres for ray sampling.
        train_frames: indices usable as training targets and as source views.
        eval_frames: held-out targets, disjoint from ``train_frames`` (except under a dataset's explicitly named
            ``paper_parity`` protocol, which reproduces the reference code's overlap); never used as sources.
        load_frame: ``index -> Frame``; the dataset decides caching.
        labelled: False for a scene without semantic labels (a user's own capture): its frames' ``semantic`` is all
            the dataset's ``ignore_index``, and no label metric is computed on it (reported as not available).
        sparse_points: ``() -> ScenePoints``, the scene's sparse points read on demand (a capture's structure from
            motion), or None for a dataset without them; what a per-scene Gaussian family starts from.
    """

    name: str
    c2w: Tensor
    intrinsics: Tensor
    height: int
    width: int
    near: float
    far: float
    train_frames: tuple[int, ...]
    eval_frames: tuple[int, ...]
    load_frame: Callable[[int], Frame] = field(repr=False, compare=False)
    labelled: bool = True
    sparse_points: Callable[[], ScenePoints] | None = field(default=None, repr=False, compare=False)

    @property
    def num_frames(self) -> int:
        return int(self.c2w.shape[0])


@dataclass(frozen=True)
class SourceViews:
    """Source (reference) images of one target and their cameras.

    Attributes:
        rgb: ``[V, 3, H, W]`` float32 in [0, 1].
        intrinsics: ``[V, 3, 3]``; c2w: ``[V, 4, 4]``.
        depth: ``[V, H, W]`` float32 metres (camera z), 0 where unknown, or None where none was loaded. Read only by
            families that take source-view depth as input (Semantic-Ray and NeuRay's depth variant), and by GP-NeRF's
            ``model.depth_source=source_depth`` sampler.
        scene, frames: the scene and frame indices the views are (``FrameCache.source_views``), or None for views
            that are no dataset's frames; a feature provider reads a frame's features by them (its on-disk cache).
    """

    rgb: Tensor
    intrinsics: Tensor
    c2w: Tensor
    depth: Tensor | None = None
    scene: str | None = None
    frames: tuple[int, ...] | None = None

    @property
    def num_views(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.rgb.shape[-2]), int(self.rgb.shape[-1])


@dataclass(frozen=True)
class FeatureMaps:
    """Output of a feature extractor for a batch of images.

    Attributes:
        radiance: ``[N, C_rad, H_r, W_r]`` low-level features for the radiance field (GNT: 32 at 1/4).
        semantic: ``[N, C_sem, H_s, W_s]`` multi-scale features for the semantic field, the levels
            concatenated along channels (GP-NeRF: 4 x 128 at 1/2), or None for a radiance-only extractor.
    """

    radiance: Tensor
    semantic: Tensor | None


@dataclass(frozen=True)
class TargetCamera:
    """The camera of a target (novel) view.

    Attributes:
        intrinsics: ``[3, 3]`` pinhole matrix at ``height`` x ``width``.
        c2w: ``[4, 4]`` camera-to-world pose (OpenCV).
        height, width: image size in pixels.
        near, far: depth bounds in metres for ray sampling.
        image: ``[H, W, 3]`` the target frame's real RGB in [0, 1], given only to a family that segments images
            (``Capabilities.segments_image``: a 2D baseline) where a real frame exists (evaluation); None otherwise.
    """

    intrinsics: Tensor
    c2w: Tensor
    height: int
    width: int
    near: float
    far: float
    image: Tensor | None = None

    @property
    def image_size(self) -> tuple[int, int]:
        return self.height, self.width


@dataclass(frozen=True)
class TargetView:
    """One target view of a training step: what the model renders and what the loss set compares it with.

    Made by the step sampler; every tensor is on the training device.

    Attributes:
        scene: scene name; frame: the target's frame index in the scene.
        camera: the target camera.
        image: ``[3, H, W]`` target RGB in [0, 1] (ground truth, and the teacher's input).
        depth: ``[H, W]`` target depth in metres, 0 = unknown.
        labels: ``[H, W]`` int64 class ids or the dataset's ignore index.
        sources: the chosen source views (None for a per-scene model, which renders from its own parameters).
        instances: ``[H, W]`` int64 instance ids (``Frame.instance``), or None when the dataset has none.
        pixels: ``[R, 2]`` the chosen target pixels ``(u, v)`` of a ray batch; the rays are cast through them (the one
            copy). None in a whole-image batch (``whole_image``).
        render_seed: seeds this view's stochastic rendering (sample jitter, importance sampling), so a view
            renders the same on any rank and at any world size.
        whole_image: the view is rendered whole (``Capabilities.trains_on`` is ``TrainingBatch.IMAGES``: a family that
            rasterizes Gaussians): no pixels are drawn and the family returns an ``ImageOutput``. False: ``pixels``
            holds R pixels drawn at random.
        valid: ``[H, W]`` bool, False where the capture's mask excludes the pixel (``Frame.valid``), in a whole-image
            batch only (a ray batch draws its pixels inside the mask); None when every pixel counts.
    """

    scene: str
    frame: int
    camera: TargetCamera
    image: Tensor
    depth: Tensor
    labels: Tensor
    sources: SourceViews | None
    pixels: Tensor | None
    render_seed: int
    instances: Tensor | None = None
    whole_image: bool = False
    valid: Tensor | None = None

    @property
    def num_rays(self) -> int:
        """Pixels rendered: the ray batch's R, or every pixel of a whole image."""
        if self.pixels is None:
            return self.camera.height * self.camera.width
        return int(self.pixels.shape[0])


@dataclass(frozen=True)
class StepBatch:
    """The target views one process trains on in one step (its share of the global batch)."""

    views: tuple[TargetView, ...]

    @property
    def num_rays(self) -> int:
        return sum(view.num_rays for view in self.views)


@dataclass(frozen=True)
class RayBatch:
    """Rays cast from the target camera.

    Attributes:
        origins: ``[R, 3]`` world positions of the camera centre.
        directions: ``[R, 3]`` world directions scaled so that their camera-z component is 1, so a point at
            parameter ``t`` along the ray has camera depth ``t``.
        pixels: ``[R, 2]`` ``(u, v)`` target pixel coordinates the rays go through.
        near, far: ``[R]`` depth bounds in metres.
    """

    origins: Tensor
    directions: Tensor
    pixels: Tensor
    near: Tensor
    far: Tensor

    @property
    def num_rays(self) -> int:
        return int(self.origins.shape[0])

    def chunk(self, start: int, stop: int) -> "RayBatch":
        return RayBatch(
            self.origins[start:stop],
            self.directions[start:stop],
            self.pixels[start:stop],
            self.near[start:stop],
            self.far[start:stop],
        )


@dataclass(frozen=True)
class RaySamples:
    """Points along each ray.

    Attributes:
        depths: ``[R, S]`` camera depths in metres, ascending along each ray.
        points: ``[R, S, 3]`` world positions ``origin + depth * direction``.
    """

    depths: Tensor
    points: Tensor


def _sample(maps: Tensor, grid: Tensor) -> Tensor:
    """``grid_sample`` of ``[V, C, h, w]`` maps at ``[V, N, 1, 2]`` coordinates -> ``[V, C, N, 1]``."""
    return F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


@dataclass(frozen=True)
class SampledMaps:
    """Feature maps of V source views at the projections of R x S ray samples, sampled when read.

    The dense tensor ``[R, S, V, C]`` is large (2,048 rays x 64 samples x 10 views x 512 channels = 2.7 GB in float32)
    and a consumer that reduces over views only ever needs one view of it at a time: ``view`` samples one view,
    ``dense`` all of them.

    Attributes:
        maps: ``[V, C, h, w]`` source feature maps.
        grid: ``[V, R * S, 1, 2]`` ``grid_sample`` coordinates of the samples in each view (``geometry.projection.normalized_grid``).
        num_rays, num_samples: R and S.
    """

    maps: Tensor
    grid: Tensor
    num_rays: int
    num_samples: int

    @property
    def num_views(self) -> int:
        return int(self.maps.shape[0])

    @property
    def channels(self) -> int:
        return int(self.maps.shape[1])

    def view(self, index: int, dtype: torch.dtype | None = None) -> Tensor:
        """``[C, R, S]`` features of view ``index`` (zeros where a sample projects outside it).

        ``dtype``: sample in this precision (as autocast would have), whatever the maps' own.
        """
        maps, grid = self.maps[index : index + 1], self.grid[index : index + 1]
        if dtype is not None:
            maps, grid = maps.to(dtype), grid.to(dtype)
        sampled = _sample(maps, grid)
        return sampled.view(self.channels, self.num_rays, self.num_samples)

    def dense(self) -> Tensor:
        """``[R, S, V, C]`` features of every view."""
        sampled = _sample(self.maps, self.grid)[..., 0]  # [V, C, N]
        return sampled.permute(2, 0, 1).reshape(self.num_rays, self.num_samples, self.num_views, self.channels)


@dataclass(frozen=True)
class ProjectedFeatures:
    """Source-view features sampled at the projections of every ray sample.

    Attributes:
        rgb_features: ``[R, S, V, 3 + C_rad]`` source RGB then radiance features.
        semantic: the source semantic maps at the samples (``SampledMaps``: ``.view(v)`` ``[C_sem, R, S]``,
            ``.dense()`` ``[R, S, V, C_sem]``), or None when not requested.
        ray_diff: ``[R, S, V, 4]`` unit difference between the point-to-target-camera and
            point-to-source-camera directions, and their dot product (GNT's pose feature).
        visible: ``[R, S, V]`` bool, the point lies in front of the source camera and inside its image.
    """

    rgb_features: Tensor
    semantic: SampledMaps | None
    ray_diff: Tensor
    visible: Tensor


@dataclass(frozen=True)
class FieldBlockOutput:
    """One block of a field aggregator.

    Attributes:
        tokens: ``[R, S, D]`` updated per-sample tokens.
        view_attention: ``[R, S, V, A]`` the attention over views this block used, A attention channels
            (softmax over V for every channel; post-dropout, exactly as it weighted the values).
    """

    tokens: Tensor
    view_attention: Tensor


@dataclass(frozen=True)
class RayBlockOutput:
    """One block of a ray aggregator.

    Attributes:
        tokens: ``[R, S, D]`` updated per-sample tokens.
        ray_attention: ``[R, H, S, S]`` attention of each of H heads (rows: queries, softmax over the last dim).
    """

    tokens: Tensor
    ray_attention: Tensor


@dataclass(frozen=True)
class RayReadout:
    """What a ray aggregator reads out of its final tokens.

    Attributes:
        rgb: ``[R, 3]`` colour (unbounded for GNT; clamp before metrics).
        weights: ``[R, S]`` per-sample weights summing to 1 along each ray.
    """

    rgb: Tensor
    weights: Tensor


@dataclass(frozen=True)
class RenderedRays:
    """Everything one rendering pass produces for a batch of rays.

    A ray-marching family fills every field it renders; a family that rasterizes primitives (3D Gaussians) has no
    samples along its rays and leaves ``weights``, ``samples`` and ``sample_semantic`` None: what reads them (the D.G
    loss, importance sampling) refuses such a family in one line.

    Attributes:
        rgb: ``[R, 3]``; depth: ``[R]`` metres (``sum_s weights * depths`` for a ray-marching family; a rasterizing
            one's composited depth).
        weights: ``[R, S]`` per-sample weights along each ray, or None for a family without samples.
        samples: the samples the pass used, or None for a family without samples.
        semantic: ``[R, C_sem]`` rendered semantic features, or None when the semantic field is off.
        features: ``[R, C]`` the rendered feature field at the rays (a feature provider's channels, decoded), or None
            (no feature field: ``+feature_provider`` not configured).
        sample_semantic: ``[R, S, C_sem]`` per-sample semantic features (for the D.G loss), or None.
        logits: ``[R, K]`` per-ray scores of a label-rendering model (``SemanticMode.LABEL_RENDERING``: per-sample
            scores composited along the ray, or per-primitive scores composited per pixel), or None.
    """

    rgb: Tensor
    depth: Tensor
    weights: Tensor | None = None
    samples: RaySamples | None = None
    semantic: Tensor | None = None
    sample_semantic: Tensor | None = None
    logits: Tensor | None = None
    features: Tensor | None = None


@dataclass(frozen=True)
class HeadOutput:
    """Output of a perception head.

    Attributes:
        logits: ``[N, K, H, W]`` per-pixel scores at the requested output size: K classes, or for an instance head
            (``Predicts.INSTANCES``) ``slots + 1`` channels whose softmax gives each slot's
            probability, the last channel being "no instance".
    """

    logits: Tensor


@dataclass(frozen=True)
class ViewOutput:
    """What a ray family's forward pass produces for one target view (R rays), before any loss.

    Attributes:
        coarse, fine: the rendering passes (fine is None with no importance samples).
        teacher_map: ``[1, C_sem, h, w]`` semantic map the extractor computes on the target image itself (None when
            semantics are off).
        teacher_at_rays: ``[R, C_sem]`` the teacher map at the rays' pixels, NOT detached (the loss set decides
            whether the gradient is blocked), or None.
        head_input: ``[1, C_sem, h, w]`` the map the head decoded: the fused map (rendered features written into
            the teacher map) or the teacher map alone, or None.
        logits: ``[1, K, H, W]`` head output at the target's size, or None.
        extras: what the family's own hooks and loss terms read from this view (``TrainingState.outputs``); the core
            never reads it.
    """

    coarse: RenderedRays
    fine: RenderedRays | None
    teacher_map: Tensor | None = None
    teacher_at_rays: Tensor | None = None
    head_input: Tensor | None = None
    logits: Tensor | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)

    @property
    def last(self) -> RenderedRays:
        """The pass that carries semantics: fine when present, else coarse."""
        return self.fine if self.fine is not None else self.coarse


@dataclass(frozen=True)
class ImageOutput:
    """What the forward pass of a family that renders whole images (``TrainingBatch.IMAGES``) produces for one target
    view: images, never its pixels as rays.

    Attributes:
        rgb: ``[H, W, 3]`` (unclamped).
        depth: ``[H, W]`` metres (camera z), 0 where nothing was rendered.
        alpha: ``[H, W]`` accumulated opacity in [0, 1], or None.
        scores: ``[1, K, H, W]`` per-pixel scores rendered without a head (``SemanticMode.LABEL_RENDERING``: each
            Gaussian's class or instance scores composited), or None.
        semantic: ``[1, C_sem, h, w]`` the rendered semantic feature map (what a head decodes, and what the 2D
            distillation compares with ``teacher_map``), or None.
        teacher_map: ``[1, C_sem, h, w]`` the extractor's semantic map of the target image itself, NOT detached (the
            loss set decides whether the gradient is blocked), or None.
        logits: ``[1, K, H, W]`` the head's output on ``semantic``, or None.
        extras: what the family's own hooks and loss terms read from this view (the rasterizer's projected centres
            ``means2d`` and footprints ``radii``: ``TrainingState.outputs``); the core never reads it.
        features: ``[1, C, h, w]`` the rendered feature field in a feature provider's channels (decoded where the model
            keeps them compressed), at any grid the provider's grid divides (the image's, say): the distillation term
            averages it over each provider cell (``gpnerf_core.features.distillation``); None without a field.
    """

    rgb: Tensor
    depth: Tensor
    alpha: Tensor | None = None
    scores: Tensor | None = None
    semantic: Tensor | None = None
    teacher_map: Tensor | None = None
    logits: Tensor | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)
    features: Tensor | None = None

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.rgb.shape[0]), int(self.rgb.shape[1])


@dataclass(frozen=True)
class Prediction:
    """A whole target view rendered on a stride grid, and its per-pixel scores (``ModelFamily.predict``).

    Attributes:
        rgb: ``[h, w, 3]`` (unclamped); depth: ``[h, w]`` metres.
        semantic: ``[C, h, w]`` rendered semantic features, or None (a model without them).
        logits: ``[1, K, H, W]`` per-pixel scores at the full image size (a head's on the rendered map, or label
            rendering's), or None.
        stride: pixels of the full image per rendered cell (h = H / stride).
        features: ``[C, h, w]`` the rendered feature field: a feature provider's 2D features distilled into the model,
            in the provider's own channels (decoded where the model keeps them compressed), or None (no feature field).
    """

    rgb: Tensor
    depth: Tensor
    semantic: Tensor | None
    logits: Tensor | None
    stride: int
    features: Tensor | None = None

    def check_finite(self, owners: Mapping[str, str], where: str) -> None:
        """Raise NonFiniteError when an output holds NaN or Inf, naming the part that made it first.

        Args:
            owners: who made each output, by name (``colour``, ``depth``, ``semantic map``, ``logits``):
                ``ModelFamily.output_owners``; ``feature field`` defaults to the model.
            where: the view, for the message (``scene 'x' frame 3``).
        """
        parts = (("colour", self.rgb), ("depth", self.depth), ("semantic map", self.semantic), ("logits", self.logits),
                 ("feature field", self.features))
        for output, value in parts:
            if value is not None and not all_finite(value):
                owner = owners.get(output, "model")
                raise NonFiniteError(f"{where}: the {owner} gave NaN or Inf ({output}); nothing was scored")


@dataclass(frozen=True)
class StepOutput:
    """The model's forward pass over a ``StepBatch``: one output per target view, in batch order: a ``ViewOutput``
    (rays) or, from a family that trains on whole images, an ``ImageOutput``."""

    views: tuple[ViewOutput | ImageOutput, ...]


@dataclass(frozen=True)
class LossInputs:
    """Everything a loss set may read for one target view of a ray family (R rays).

    Attributes:
        coarse, fine: the two rendering passes (fine is None with no importance samples).
        target_rgb: ``[R, 3]``; target_depth: ``[R]`` metres, 0 = unknown.
        logits: ``[1, K, H, W]`` head output on the fused map, or None without a head.
        labels: ``[1, H, W]`` int64 target labels with ``ignore_index``.
        teacher_at_rays: ``[R, C_sem]`` target-view semantic features at the rays' pixels, NOT detached:
            the loss set decides whether the gradient is blocked.
        ignore_index: label value excluded from CE and metrics.
        instances: ``[1, H, W]`` int64 target instance ids, or None unless the loss set ``needs_instances``.
        labels_at_rays: ``[R]`` the target labels at the rays' pixels (for per-ray scores, ``RenderedRays.logits``),
            or None without labels.
        instances_at_rays: ``[R]`` the target instance ids at the rays' pixels (for per-ray instance scores), or None
            unless the loss set ``needs_instances`` and the model renders per-ray scores.
    """

    coarse: RenderedRays
    fine: RenderedRays | None
    target_rgb: Tensor
    target_depth: Tensor
    logits: Tensor | None
    labels: Tensor | None
    teacher_at_rays: Tensor | None
    ignore_index: int
    instances: Tensor | None = None
    labels_at_rays: Tensor | None = None
    instances_at_rays: Tensor | None = None

    @property
    def last(self) -> RenderedRays:
        """The pass that carries semantics: fine when present, else coarse."""
        return self.fine if self.fine is not None else self.coarse


@dataclass(frozen=True)
class ImageLossInputs:
    """Everything a loss set may read for one target view of a family that renders whole images.

    Attributes:
        output: what the family rendered (``ImageOutput``: images and maps).
        target_rgb: ``[H, W, 3]`` in [0, 1]; target_depth: ``[H, W]`` metres, 0 = unknown.
        labels: ``[H, W]`` int64 class ids with ``ignore_index``, or None when no term reads them.
        ignore_index: label value excluded from CE and metrics.
        instances: ``[H, W]`` int64 instance ids, or None unless the loss set ``needs_instances``.
        valid: ``[H, W]`` bool, False at pixels a capture's mask excludes (rendered, but no term may read them), or
            None when every pixel counts.
    """

    output: ImageOutput
    target_rgb: Tensor
    target_depth: Tensor
    labels: Tensor | None
    ignore_index: int
    instances: Tensor | None = None
    valid: Tensor | None = None
