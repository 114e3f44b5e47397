"""Small synthetic inputs for the contract checks, each drawn from its own seeded generator (CPU, float32).

The sizes are deliberately small and odd (7 x 9 maps, 5 rays, 3 views) so that a component which hard-codes a
size, or mixes up two axes of equal length, fails.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import Tensor

from gpnerf_core.geometry import points_along_rays, rays_through_pixels, stratified_inverse_depths
from gpnerf_core.types import (
    Frame,
    ImageLossInputs,
    ImageOutput,
    LossInputs,
    ProjectedFeatures,
    RayBatch,
    RaySamples,
    RenderedRays,
    Scene,
    SourceViews,
    StepBatch,
    TargetCamera,
    TargetView,
)

HEAD_IN_DIM = 32
"""``in_dim`` the kit passes to heads: 4 levels of 8 channels."""
HEAD_LEVELS = 4
HEAD_CLASSES = (1, 3, 51)
"""``num_outputs`` values every head must honour (51: Replica's classes)."""
HEAD_CASES = (
    # (N, K, map size, output size): same size, a non-multiple upsampling, an exact multiple, a downsizing.
    (1, 3, (8, 12), (8, 12)),
    (2, 51, (7, 9), (37, 45)),
    (1, 1, (5, 11), (10, 22)),
    (1, 3, (16, 24), (7, 9)),
)
EXTRACTOR_SIZES = ((1, 32, 48), (2, 64, 32))
"""``(N, H, W)`` images every extractor must encode (multiples of 16)."""
EXTRACTOR_OTHER_SIZES = ((1, 40, 36), (1, 33, 47))
"""Sizes an extractor may refuse with a ``GpnerfError``; when it accepts them its maps must still be right."""
FIELD_IN_DIM = 11
"""``in_dim`` of field aggregators: 3 RGB + an 8-channel radiance map."""
RAY_IN_DIM = 24
"""``in_dim`` of ray aggregators (divisible by 1, 2, 3, 4, 6, 8, 12 and 24 heads)."""
RAY_BLOCKS = 2
"""``num_blocks`` of ray aggregators (the field aggregator's, in the pipeline)."""
AGGREGATOR_CASES = ((5, 7, 3), (2, 3, 1))
"""``(R, S, V)``: rays, samples per ray, source views."""
LOSS_RAYS, LOSS_SAMPLES, LOSS_CHANNELS = 6, 5, 8


def generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def head_features(n: int, size: tuple[int, int], *, dim: int = HEAD_IN_DIM, seed: int = 0) -> Tensor:
    """``[N, dim, h, w]`` standard-normal features."""
    return torch.randn(n, dim, *size, generator=generator(seed))


def images(n: int, height: int, width: int, *, seed: int = 0) -> Tensor:
    """``[N, 3, H, W]`` uniform images in [0, 1]."""
    return torch.rand(n, 3, height, width, generator=generator(seed))


def ray_batch(rays: int, *, seed: int = 0) -> RayBatch:
    """Rays of a 16 x 12 pinhole camera at the origin, 0.5 m to 4 m."""
    g = generator(seed)
    pixels = torch.rand(rays, 2, generator=g) * torch.tensor([15.0, 11.0])
    intrinsics = torch.tensor([[12.0, 0.0, 7.5], [0.0, 12.0, 5.5], [0.0, 0.0, 1.0]])
    return rays_through_pixels(pixels, intrinsics, torch.eye(4), 0.5, 4.0)


def ray_samples(rays: RayBatch, samples: int) -> RaySamples:
    return points_along_rays(rays, stratified_inverse_depths(rays, samples, perturb=False))


def projected(
    rays: int, samples: int, views: int, *, in_dim: int = FIELD_IN_DIM, zeros: bool = False, seed: int = 0
) -> tuple[ProjectedFeatures, RaySamples, RayBatch]:
    """Projected source features for ``FieldAggregator.begin``.

    Sample 0 of ray 0 is seen by no view, and so is every sample of the last ray when there are two rays or
    more (a ray that leaves every source frustum). With ``zeros`` every feature is 0.
    """
    g = generator(seed)
    batch = ray_batch(rays, seed=seed)
    visible = torch.rand(rays, samples, views, generator=g) > 0.2
    visible[0, 0] = False
    if rays > 1:
        visible[-1] = False
    features = torch.randn(rays, samples, views, in_dim, generator=g)
    ray_diff = torch.nn.functional.normalize(torch.randn(rays, samples, views, 4, generator=g), dim=-1)
    if zeros:
        features, ray_diff = torch.zeros_like(features), torch.zeros_like(ray_diff)
    projected_features = ProjectedFeatures(rgb_features=features, semantic=None, ray_diff=ray_diff, visible=visible)
    return projected_features, ray_samples(batch, samples), batch


def tokens(rays: int, samples: int, *, dim: int = RAY_IN_DIM, seed: int = 0) -> Tensor:
    """``[R, S, D]`` standard-normal tokens, as a field aggregator's block returns them."""
    return torch.randn(rays, samples, dim, generator=generator(seed))


def rendered(*, rays: int = LOSS_RAYS, samples: int = LOSS_SAMPLES, channels: int = LOSS_CHANNELS,
             semantic: bool = True, sample_semantic: bool = True, zeros: bool = False, seed: int = 0,
             scores: int = 0) -> RenderedRays:
    """One rendering pass whose float tensors require gradients (the semantic ones only when asked for; ``scores``
    per-ray scores ``[R, scores]`` as a label-rendering family composites them, 0: none)."""
    g = generator(seed)

    def leaf(*shape: int) -> Tensor:
        value = torch.zeros(*shape) if zeros else torch.randn(*shape, generator=g)
        return value.requires_grad_()

    batch = ray_batch(rays, seed=seed)
    samples_ = ray_samples(batch, samples)
    weights = torch.softmax(torch.randn(rays, samples, generator=g), dim=-1).requires_grad_()
    return RenderedRays(
        rgb=leaf(rays, 3),
        weights=weights,
        depth=(weights * samples_.depths).sum(-1),
        samples=samples_,
        semantic=leaf(rays, channels) if semantic else None,
        sample_semantic=leaf(rays, samples, channels) if sample_semantic else None,
        logits=leaf(rays, scores) if scores else None,
    )


def loss_inputs(
    *,
    semantics: bool,
    sample_semantics: bool,
    classes: int = 4,
    fine: bool = True,
    zeros: bool = False,
    ignore_all: bool = False,
    instances: bool = False,
    instance_ids: int = 3,
    seed: int = 0,
    whole_image: bool = False,
) -> LossInputs | ImageLossInputs:
    """What the trainer passes a loss set for one target view, shaped by the loss set's ``needs_*`` flags.

    Without ``semantics`` the logits, labels and teacher are None and the passes carry no semantic features, as
    in the pipeline. ``zeros`` zeroes every feature and the target depth (unknown); ``ignore_all`` labels every
    pixel with the ignore index. ``instances`` adds target instance ids (``instance_ids`` of them; ``zeros``: one), for
    a loss set that ``needs_instances``; its logits then have ``classes`` = slots + 1 channels. With ``semantics`` each
    pass also carries per-ray scores of ``classes`` channels, and the labels (and instance ids) at the rays, for the
    loss sets of label-rendering families. ``whole_image``: ``ImageLossInputs`` of a 6 x 7 target instead
    (``image_loss_inputs``), for a loss set that ``needs_whole_images``.
    """
    if whole_image:
        return image_loss_inputs(semantics=semantics, classes=classes, zeros=zeros, ignore_all=ignore_all,
                                 instances=instances, instance_ids=instance_ids, seed=seed)
    g = generator(seed + 1)
    height, width = 6, 7
    rays = LOSS_RAYS
    passes = dict(rays=rays, semantic=semantics, sample_semantic=sample_semantics, zeros=zeros,
                  scores=classes if semantics else 0)
    labels = torch.randint(0, classes, (1, height, width), generator=g)
    if ignore_all:
        labels.fill_(255)
    teacher = torch.zeros(rays, LOSS_CHANNELS) if zeros else torch.randn(rays, LOSS_CHANNELS, generator=g)
    logits = torch.zeros(1, classes, height, width) if zeros else torch.randn(1, classes, height, width, generator=g)
    return LossInputs(
        coarse=rendered(seed=seed, **passes),
        fine=rendered(seed=seed + 2, **passes) if fine else None,
        target_rgb=torch.rand(rays, 3, generator=g),
        target_depth=torch.zeros(rays) if zeros else torch.rand(rays, generator=g) + 0.5,
        logits=logits.requires_grad_() if semantics else None,
        labels=labels if semantics else None,
        teacher_at_rays=teacher.requires_grad_() if semantics else None,
        ignore_index=255,
        instances=(torch.zeros if zeros else lambda *s: torch.randint(0, instance_ids, s, generator=g))(
            1, height, width).long() if instances and semantics else None,
        labels_at_rays=labels.reshape(-1)[:rays] if semantics else None,
        instances_at_rays=(torch.zeros(rays, dtype=torch.long) if zeros else torch.randint(
            0, instance_ids, (rays,), generator=g)) if instances and semantics else None,
    )


def image_loss_inputs(*, semantics: bool, classes: int = 4, zeros: bool = False, ignore_all: bool = False,
                      instances: bool = False, instance_ids: int = 3, seed: int = 0) -> ImageLossInputs:
    """What the trainer passes a loss set for one target view of a family that renders whole images: a 6 x 7
    ``ImageOutput`` whose float tensors require gradients (colour, depth, opacity; with ``semantics`` also per-pixel
    scores and head logits of ``classes`` channels, a 3 x 4 semantic map and the target's own map), and the target
    images. The options are ``loss_inputs``'s."""
    g = generator(seed + 1)
    height, width, map_size = 6, 7, (3, 4)

    def leaf(*shape: int) -> Tensor:
        value = torch.zeros(*shape) if zeros else torch.randn(*shape, generator=g)
        return value.requires_grad_()

    output = ImageOutput(
        rgb=leaf(height, width, 3),
        depth=torch.zeros(height, width) if zeros else torch.rand(height, width, generator=g) + 0.5,
        alpha=torch.ones(height, width) if zeros else torch.rand(height, width, generator=g),
        scores=leaf(1, classes, height, width) if semantics else None,
        semantic=leaf(1, LOSS_CHANNELS, *map_size) if semantics else None,
        teacher_map=leaf(1, LOSS_CHANNELS, *map_size) if semantics else None,
        logits=leaf(1, classes, height, width) if semantics else None,
    )
    labels = torch.randint(0, classes, (height, width), generator=g)
    if ignore_all:
        labels.fill_(255)
    ids = (torch.zeros if zeros else lambda *s: torch.randint(0, instance_ids, s, generator=g))(height, width).long()
    return ImageLossInputs(
        output=output,
        target_rgb=torch.rand(height, width, 3, generator=g),
        target_depth=torch.zeros(height, width) if zeros else torch.rand(height, width, generator=g) + 0.5,
        labels=labels if semantics else None,
        ignore_index=255,
        instances=ids if instances and semantics else None,
    )


def loss_leaves(inputs: LossInputs | ImageLossInputs) -> dict[str, Tensor]:
    """The tensors of ``inputs`` that require gradients, by a readable name (``fine.semantic``, ``logits``,
    ``image.scores``)."""
    if isinstance(inputs, ImageLossInputs):
        leaves = {f"image.{name}": getattr(inputs.output, name)
                  for name in ("rgb", "scores", "semantic", "teacher_map", "logits")}
        return {name: t for name, t in leaves.items() if t is not None and t.requires_grad}
    leaves = {"logits": inputs.logits, "teacher_at_rays": inputs.teacher_at_rays}
    for name, rays in (("coarse", inputs.coarse), ("fine", inputs.fine)):
        if rays is not None:
            for field in ("rgb", "weights", "semantic", "sample_semantic", "logits"):
                leaves[f"{name}.{field}"] = getattr(rays, field)
    return {name: t for name, t in leaves.items() if t is not None and t.requires_grad}


def cameras(count: int, *, radius: float = 2.0, seed: int = 0) -> Tensor:
    """``[count, 4, 4]`` OpenCV camera-to-world poses on a jittered circle, each looking at the origin."""
    g = generator(seed)
    angles = torch.arange(count) * (2 * math.pi / max(count, 1)) + 0.1 * torch.rand(count, generator=g)
    poses = torch.eye(4).repeat(count, 1, 1)
    for i, angle in enumerate(angles.tolist()):
        centre = torch.tensor([radius * math.cos(angle), 0.3 * math.sin(3 * angle), radius * math.sin(angle)])
        forward = torch.nn.functional.normalize(-centre, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, -1.0, 0.0]), forward), dim=0)
        down = torch.linalg.cross(forward, right)
        poses[i, :3, :3] = torch.stack([right, down, forward], dim=1)
        poses[i, :3, 3] = centre
    return poses


KIT_CLASSES = 3
"""Classes of the synthetic scene a model family is checked on."""
KIT_HEAD = {"name": "unet", "channels": 16, "norm_groups": 4}
"""The head a model family that decodes with one is checked with: the built-in U-Net, small."""
KIT_SAMPLES = {"coarse_samples": 6, "fine_samples": 2}
"""Samples per ray of a model family under check."""


def kit_parts(registry: Any, model: str, *, head: bool, parts: Mapping[str, Any] | None = None,
              configs: Mapping[str, Mapping[str, Any]] | None = None) -> Any:
    """``ModelParts`` of the family ``model`` at ``KIT_CLASSES``: the parts its config declares
    (``gpnerf_core.part``), and ``KIT_HEAD`` when ``head``.

    Args:
        parts: ``{kind: options}`` the family's config under check gives its parts (``{"feature_extractor": {"name":
            ..., "widths": ...}}``): another option than the declared default where it names one, and options.
        configs: ``{"<kind>/<name>": options}`` the caller gives a part's component (the kit's ``configs``), under
            ``parts``' own; a part without either is built with its defaults.
    """
    from omegaconf import OmegaConf

    from gpnerf_core.model.build import ConfiguredParts
    from gpnerf_core.registry.declarations import declared_parts

    entry = registry.components["model"].get(model)
    chosen = {}
    for kind, default in (declared_parts(entry.spec.config) if entry is not None else {}).items():
        own = dict((parts or {}).get(kind) or {})
        name = own.pop("name", default)
        if name is not None:
            chosen[kind] = {"name": name, **dict((configs or {}).get(f"{kind}/{name}") or {}), **own}
    cfg = OmegaConf.create({"model": {"name": model, **chosen}, "head": dict(KIT_HEAD) if head else None})
    return ConfiguredParts(cfg, KIT_CLASSES, registry)


HEIGHT, WIDTH = 32, 48
KIT_INTRINSICS = torch.tensor([[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])


def _pose(x: float) -> Tensor:
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return c2w


def model_view(*, sources: bool = True, seed: int = 0) -> tuple[TargetCamera, SourceViews | None]:
    """A 32 x 48 target camera at the origin looking down +z (0.5 m to 4 m) and two source views 0.1 m to either
    side (None without ``sources``: a per-scene family)."""
    camera = TargetCamera(KIT_INTRINSICS.clone(), _pose(0.0), HEIGHT, WIDTH, 0.5, 4.0)
    if not sources:
        return camera, None
    views = SourceViews(rgb=images(2, HEIGHT, WIDTH, seed=seed), intrinsics=KIT_INTRINSICS.expand(2, 3, 3).clone(),
                        c2w=torch.stack([_pose(-0.1), _pose(0.1)]))
    return camera, views


def model_scene() -> Scene:
    """The synthetic scene ``model_view`` and ``model_batch`` look at, as a dataset gives it: three 32 x 48 frames at
    -0.1, 0 and 0.1 m, each with random colours and depth (1 to 3 m) and labels (what a per-scene family's
    ``initialise`` is given); the middle one held out."""
    poses = torch.stack([_pose(-0.1), _pose(0.0), _pose(0.1)])

    def frame(index: int) -> Frame:
        g = generator(200 + index)
        return Frame(rgb=images(1, HEIGHT, WIDTH, seed=20 + index)[0].permute(1, 2, 0).contiguous(),
                     depth=torch.rand(HEIGHT, WIDTH, generator=g) * 2 + 1,
                     semantic=torch.randint(KIT_CLASSES, (HEIGHT, WIDTH), generator=g),
                     intrinsics=KIT_INTRINSICS.clone(), c2w=poses[index].clone())

    return Scene(name="kit", c2w=poses, intrinsics=KIT_INTRINSICS.expand(3, 3, 3).clone(), height=HEIGHT, width=WIDTH,
                 near=0.5, far=4.0, train_frames=(0, 2), eval_frames=(1,), load_frame=frame)


def model_batch(*, sources: bool = True, views: int = 2, rays: int = 12, whole_images: bool = False) -> StepBatch:
    """A step of ``views`` target views of the synthetic scene, ``rays`` pixels each (no pixels with ``whole_images``:
    ``TargetView.whole_image``), labels in ``[0, KIT_CLASSES)``."""
    targets = []
    for index in range(views):
        g = generator(100 + index)
        camera, source_views = model_view(sources=sources, seed=index)
        flat = torch.randperm(HEIGHT * WIDTH, generator=g)[:rays]
        pixels = None if whole_images else torch.stack([flat % WIDTH, flat // WIDTH], -1).float()
        targets.append(TargetView(
            scene="kit", frame=index, camera=camera, image=images(1, HEIGHT, WIDTH, seed=10 + index)[0],
            depth=torch.rand(HEIGHT, WIDTH, generator=g) * 2 + 1, labels=torch.randint(KIT_CLASSES, (HEIGHT, WIDTH), generator=g),
            sources=source_views, pixels=pixels, render_seed=7 + index,
            instances=torch.randint(3, (HEIGHT, WIDTH), generator=g), whole_image=whole_images,
        ))
    return StepBatch(tuple(targets))
