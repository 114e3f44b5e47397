"""A second model family, written against the public surface only, as a third party would: ``model=pooled_views``.

IBRNet-style (Wang et al., CVPR 2021, simplified): each sample is projected into the source views (the core's
``Projector``) and encoded by the configured ``feature_extractor``; the per-view features are pooled into their mean
and variance over the views that see the sample; an MLP of each view's feature and the pooled statistics gives a
per-view hidden vector, whose own mean and variance give the density (softplus) and, through a linear layer, the
sample's class scores; the colour is the source colours blended by a softmax over the views. Density is composited
along the ray (``density_opacity`` with the sample intervals), and so are the class scores: label rendering. Both
passes (coarse, then coarse + importance samples) use one network. What IBRNet has and this does not: the ray
transformer over the samples' density features, a separate fine network, direction differences in the blending.

Registered by ``gpnerf_register_models`` below: in-process through ``registry_with_family()``, and for the
subprocesses of the command tests as an installed plugin (``install(root)``; put ``root`` and this folder on
``PYTHONPATH``). No core file knows it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    ComponentSpec,
    ConfigError,
    FeatureMaps,
    ModelConfig,
    RayMarchingConfig,
    ModelFamily,
    ModelParts,
    Prediction,
    Predicts,
    Projector,
    RayBatch,
    RaySamples,
    RenderedRays,
    SemanticMode,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    ViewOutput,
    composite,
    compositing_weights,
    density_opacity,
    hookimpl,
    importance_depths,
    part,
    points_along_rays,
    rays_through_pixels,
    render_whole_view,
    stratified_inverse_depths,
)

DISTRIBUTION = "gpnerf-test-family"


@dataclass
class PooledViewsRates:
    """Its learning-rate groups (``model.lr.<group>``)."""

    feature_extractor: float = 1e-3
    transformer: float = 5e-4
    """Its own MLPs."""


@dataclass
class PooledViewsConfig(RayMarchingConfig):
    """Options of the ``pooled_views`` family."""

    name: str = "pooled_views"
    """Registry name of this model family."""
    feature_extractor: Any = part("resunet_fpn")
    """Encodes the source views (the built-in extractor)."""
    hidden: int = 32
    """Width of the per-view and density MLPs."""
    label_rendering: bool = True
    """Render class scores (off: colour and depth only)."""
    lr: PooledViewsRates = field(default_factory=PooledViewsRates)

    runtime_keys: ClassVar[tuple[str, ...]] = ModelConfig.runtime_keys


class PooledViews(ModelFamily):
    """Mean/variance pooling over views, a density MLP, blended source colours, rendered labels.

    Args:
        extractor: the configured feature extractor (its radiance maps).
        num_classes: K scores per sample (0: no label rendering).
        coarse_samples, fine_samples: samples per ray of the two passes.
        hidden: MLP width.
    """

    capabilities = Capabilities(accepts_head=False)  # label rendering: a configured head is refused by the build

    def __init__(self, *, extractor: nn.Module, num_classes: int, coarse_samples: int, fine_samples: int,
                 hidden: int) -> None:
        super().__init__()
        if coarse_samples < 2 or fine_samples < 0 or hidden < 1:
            raise ConfigError(f"model.coarse_samples={coarse_samples}, model.fine_samples={fine_samples}, "
                              f"model.hidden={hidden}: expected >= 2, >= 0 and >= 1")
        self.extractor = extractor
        per_view = 3 + extractor.radiance_dim
        self.view_mlp = nn.Sequential(nn.Linear(3 * per_view, hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU())
        self.blend = nn.Linear(hidden, 1)
        self.density = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.ELU(), nn.Linear(hidden, 1))
        self.classes = nn.Linear(2 * hidden, num_classes) if num_classes else None
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.projector = Projector()

    @property
    def semantic_output(self) -> SemanticOutput | None:
        if self.classes is None:
            return None
        return SemanticOutput(Predicts.CLASSES, SemanticMode.LABEL_RENDERING, self.classes.out_features)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        rest = [p for name, p in self.named_parameters() if not name.startswith("extractor.")]
        return {"feature_extractor": list(self.extractor.parameters()), "transformer": rest}

    def check_image_size(self, height: int, width: int) -> None:
        self.extractor.check_image_size(height, width)

    def encode(self, images: Tensor) -> FeatureMaps:
        return self.extractor(images)

    # ---- one pass ------------------------------------------------------------------------------------------------

    def _pass(self, rays: RayBatch, samples: RaySamples, sources: SourceViews, maps: FeatureMaps,
              semantics: bool) -> RenderedRays:
        projected = self.projector(samples, rays.origins, sources, maps, with_semantic=False)
        features, seen = projected.rgb_features, projected.visible[..., None].float()  # [R, S, V, C], [R, S, V, 1]
        count = seen.sum(dim=2, keepdim=True).clamp_min(1.0)
        mean = (features * seen).sum(dim=2, keepdim=True) / count
        variance = (((features - mean) ** 2) * seen).sum(dim=2, keepdim=True) / count
        pooled = torch.cat([mean, variance], dim=-1).expand(-1, -1, features.shape[2], -1)
        hidden = self.view_mlp(torch.cat([features, pooled], dim=-1))  # [R, S, V, D]
        logits = self.blend(hidden).masked_fill(seen == 0, -1e9)
        colour = (torch.softmax(logits, dim=2) * features[..., :3]).sum(dim=2)  # [R, S, 3]
        h_mean = (hidden * seen).sum(dim=2) / count[:, :, 0]
        h_var = (((hidden - h_mean[:, :, None]) ** 2) * seen).sum(dim=2) / count[:, :, 0]
        statistics = torch.cat([h_mean, h_var], dim=-1)  # [R, S, 2D]
        density = F.softplus(self.density(statistics)[..., 0])
        weights = compositing_weights(density_opacity(density, samples.depths))
        scores = composite(weights, self.classes(statistics)) if semantics and self.classes is not None else None
        return RenderedRays(rgb=composite(weights, colour), weights=weights, depth=(weights * samples.depths).sum(-1),
                            samples=samples, logits=scores)

    def _render(self, rays: RayBatch, sources: SourceViews, maps: FeatureMaps, semantics: bool,
                generator: torch.Generator | None) -> tuple[RenderedRays, RenderedRays | None]:
        randomized = generator is not None
        depths = stratified_inverse_depths(rays, self.coarse_samples, perturb=randomized, generator=generator)
        coarse = self._pass(rays, points_along_rays(rays, depths), sources, maps, semantics)
        if not self.fine_samples:
            return coarse, None
        extra = importance_depths(depths, coarse.weights, self.fine_samples, deterministic=not randomized,
                                  generator=generator)
        fine = self._pass(rays, points_along_rays(rays, torch.cat([depths, extra], -1)), sources, maps, semantics)
        return coarse, fine

    # ---- the contract ----------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics) for view in batch.views))

    def _forward_view(self, view: TargetView, semantics: bool) -> ViewOutput:
        camera = view.camera
        rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = torch.Generator(device=view.pixels.device).manual_seed(view.render_seed) if self.training else None
        coarse, fine = self._render(rays, view.sources, self.encode(view.sources.rgb), semantics, generator)
        return ViewOutput(coarse=coarse, fine=fine)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: FeatureMaps | None = None) -> Prediction:
        if sources is None:
            raise ConfigError("pooled_views renders from source views; none were given")
        maps = features if features is not None else self.encode(sources.rgb)

        def render(rays: RayBatch) -> RenderedRays:
            coarse, fine = self._render(rays, sources, maps, self.classes is not None, None)
            return fine if fine is not None else coarse

        return render_whole_view(camera, render, stride=stride, chunk_rays=chunk_rays)


def build_pooled_views(*, parts: ModelParts, coarse_samples: int = PooledViewsConfig.coarse_samples,
                       fine_samples: int = PooledViewsConfig.fine_samples, hidden: int = PooledViewsConfig.hidden,
                       label_rendering: bool = PooledViewsConfig.label_rendering) -> PooledViews:
    if parts.configured("head"):
        raise ConfigError(f"model=pooled_views renders labels per pixel; drop +head={parts.name('head')}")
    return PooledViews(extractor=parts.build("feature_extractor"),
                       num_classes=parts.num_classes if label_rendering else 0,
                       coarse_samples=coarse_samples, fine_samples=fine_samples, hidden=hidden)


@hookimpl
def gpnerf_register_models() -> list[ComponentSpec]:
    return [ComponentSpec("pooled_views", build_pooled_views, PooledViewsConfig,
                          "IBRNet-style mean/variance pooling over views + density MLP, label rendering (tests)")]


def install(root: Path) -> Path:
    """Write a distribution into ``root`` whose ``gpnerf`` entry point is this module; returns ``root``."""
    info = root / "gpnerf_test_family-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DISTRIBUTION}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[gpnerf]\ngpnerf_test_family = model_family\n")
    return root


def registry_with_family() -> Any:
    """The built-in plugins and this family, in this process."""
    from gpnerf_core.registry.components import collect, register_config_options
    from gpnerf_core.registry.plugins import BUILTIN_PLUGINS, make_plugin_manager

    registry = collect(make_plugin_manager(builtins=(*BUILTIN_PLUGINS, "model_family"), autoload=False))
    register_config_options(registry)
    return registry
