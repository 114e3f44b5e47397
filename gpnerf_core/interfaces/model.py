"""Interface of model families: what renders a target view's rays, and the only thing every tool drives.

The trainer, the evaluator and its metrics, checkpoints, ``render``, ``view``, ``stress``, ``size``, ``bench``,
``report`` and the chart know a model only through ``ModelFamily``. A family is registered like any component
(``gpnerf_register_models``) and selected with ``model=<name>``; GP-NeRF's GNT transformers with the attention-reusing
semantic field are one family (``model=gnt``, a built-in plugin), and docs/plugins.md ("Write a model family") shows
another.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Mapping

from torch import Tensor, nn

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.depth_source import DepthSource
from gpnerf_core.interfaces.head import PerceptionHead, Predicts
from gpnerf_core.interfaces.training import GroupOptions, TrainingCallback
from gpnerf_core.interfaces.weights import ImportedWeights, ImportsWeights
from gpnerf_core.types import FeatureMaps, Prediction, Scene, SourceViews, StepBatch, StepOutput, TargetCamera

if TYPE_CHECKING:
    from gpnerf_core.geometry.gaussians.scene import GaussianScene


class TrainingBatch(str, enum.Enum):
    """What one target view of a training step is: what the family renders and the loss compares."""

    RAYS = "rays"
    """``train.rays`` pixels drawn at random (a ray-marching family: each ray costs its samples)."""
    IMAGES = "images"
    """Every pixel, in row-major order (``TargetView.whole_image``): a family that renders whole images at once
    (rasterized Gaussians), whose loss may read images (``LossInputs.as_image``, e.g. SSIM)."""


class SourceEncoding(str, enum.Enum):
    """What a generalizable family computes from its source views that can be kept between renders (the
    ``feature_cache`` of ``render``, ``view`` and ``export``)."""

    PER_VIEW = "per_view"
    """``encode(images)``: each source image encoded alone, kept per frame (a CNN on each view)."""
    SOURCE_SET = "source_set"
    """``encode_sources(sources, near, far)``: the source views encoded together (a cost volume, cross-view
    attention) into something kept per set of source frames: for a feed-forward Gaussian family, its Gaussians."""


class SemanticMode(str, enum.Enum):
    """How a model turns what it renders into per-pixel scores."""

    DECODED = "decoded"
    """Semantic features rendered per ray and decoded by a 2D head on the whole map, with image context (GP-NeRF)."""
    LABEL_RENDERING = "label_rendering"
    """Per-sample class (or instance) scores volume-rendered per pixel, each pixel on its own (Semantic-NeRF,
    Semantic-Ray, "X + semantic head")."""


@dataclass(frozen=True)
class SemanticOutput:
    """What a model's semantic output is: every tool reads this instead of asking which head or family it has.

    Attributes:
        predicts: ``Predicts.CLASSES`` (mIoU and the segmentation protocols) or ``Predicts.INSTANCES`` (instance AP).
        mode: how the scores are made (``SemanticMode``).
        num_outputs: channels of ``Prediction.logits``: the classes, or ``slots + 1`` for instances (the last channel
            is "no instance").
        slots: the instance slots (``predicts`` INSTANCES), else None.
        slot_activation: how instance scores become slot probabilities: ``softmax`` over the ``slots + 1`` channels (an
            instance head, the reference's) or ``sigmoid``, each channel on its own (DM-NeRF's); the last channel is
            dropped either way.
    """

    predicts: Predicts
    mode: SemanticMode
    num_outputs: int
    slots: int | None = None
    slot_activation: str = "softmax"


class ModelParts(ABC):
    """What the core hands a model family's factory (its ``parts`` argument) besides the family's own options.

    A family builds the other components it is made of (an extractor, aggregators, a head) from the config through
    this, so each stays a plugin of its own kind, chosen on the command line (its parts under the model,
    ``model/feature_extractor=...``; the add-ons ``+head=...``), and is never a copy inside the family. The parts it
    builds are those its config declares (``gpnerf_core.part``); ``build`` reads their sections under ``model``.
    """

    @property
    @abstractmethod
    def num_classes(self) -> int:
        """K: the classes the model predicts (the dataset's, or a checkpoint's on a dataset without a class list)."""

    @abstractmethod
    def configured(self, kind: str) -> bool:
        """The config selects a component of ``kind`` (``head`` and ``loss`` are optional, ``+head=<name>``)."""

    @abstractmethod
    def build(self, kind: str, **runtime: Any) -> Any:
        """The configured component of ``kind`` built with ``runtime`` keyword arguments (its kind's
        ``runtime_arguments``); a ConfigError when the config selects none."""

    @abstractmethod
    def head(self, *, in_dim: int, in_levels: int) -> PerceptionHead | None:
        """The configured perception head decoding ``in_dim`` channels in ``in_levels`` equal blocks, with its outputs
        (``num_classes``, or ``slots + 1`` for an instance head); None when the config has no head."""

    @abstractmethod
    def name(self, kind: str) -> str | None:
        """The configured component name of ``kind`` (None when the config selects none)."""

    def semantic_head(self, extractor: Any, family: str, decodes: str = "rendered features") -> PerceptionHead | None:
        """The configured head decoding ``extractor``'s semantic-map space (its ``semantic_dim`` channels in
        ``semantic_levels`` blocks), None without one; a ConfigError naming ``+head``, ``model={family}`` and the
        extractor when the extractor makes no semantic maps (``decodes``: what the head decodes, for the message)."""
        if not self.configured("head"):
            return None
        if not extractor.semantic_dim:
            raise ConfigError(f"+head={self.name('head')} with model={family} decodes {decodes} in the semantic maps' "
                              f"space of the feature extractor, and model/feature_extractor="
                              f"{self.name('feature_extractor')} makes none (model.feature_extractor.semantic=true, or "
                              "another extractor that makes semantic maps)")
        return self.head(in_dim=extractor.semantic_dim, in_levels=extractor.semantic_levels)

    def depth_source(self, sampler: str) -> DepthSource | None:
        """The configured ``+depth_source`` built, or None without one. It places the samples of
        ``model.sampler=depth``, so a family's ``sampler`` must be ``depth`` with it (else a ConfigError naming both)."""
        if not self.configured("depth_source"):
            return None
        if sampler != "depth":
            raise ConfigError(f"depth_source={self.name('depth_source')} places the samples of model.sampler=depth; "
                              f"expected model.sampler=depth with it (model.sampler is {sampler!r})")
        return self.build("depth_source")

    def one_pass_depth_source(self, family: str, sampler: str, samples: int) -> DepthSource | None:
        """``depth_source`` for a family whose ``model.sampler=depth`` is one pass on ``samples`` samples
        (``model.fine_samples``) around a depth source's depth: None with ``uniform``; with ``depth``, a ConfigError
        when the config selects no source or ``samples`` < 1."""
        source = self.depth_source(sampler)
        if sampler == "depth" and (source is None or samples < 1):
            raise ConfigError(f"model={family} model.sampler=depth renders one pass on model.fine_samples samples "
                              f"around a +depth_source's depth; expected +depth_source=<name> and model.fine_samples "
                              f">= 1 (model.fine_samples={samples})")
        return source


@contextlib.contextmanager
def one_pass_preview(family: nn.Module, depth_source: DepthSource, samples: int) -> Iterator[bool]:
    """``ModelFamily.preview_sampling`` of a family whose ``model.sampler=depth`` is one pass on ``fine_samples``
    samples around ``depth_source``'s depth (GNT, NeuRay, Semantic-Ray, MVSNeRF): while entered, ``family.sampling``
    says ``depth``, ``family.depth_source`` is its own (a family trained with one keeps it) or ``depth_source``, and
    ``family.fine_samples`` is ``samples``; the three are restored on exit, whatever happens. Yields True."""
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ConfigError(f"a preview needs at least 1 sample per ray, got {samples!r}")
    saved = family.sampling, family.depth_source, family.fine_samples
    family.sampling = dataclasses.replace(family.sampling, sampler="depth")
    family.depth_source = family.depth_source or depth_source
    family.fine_samples = samples
    try:
        yield True
    finally:
        family.sampling, family.depth_source, family.fine_samples = saved


class ModelFamily(ImportsWeights, nn.Module, ABC):
    """Renders colour, depth and semantics of a target view's rays; trained, evaluated, rendered and viewed unchanged.

    Built by its factory with its config fields (a subclass of ``gpnerf_core.ModelConfig``) and ``parts``
    (``ModelParts``). The core reads ``model.num_source_views``, ``model.init`` and ``model.init_strict`` itself; every
    other field goes to the factory.

    A **generalizable** family (``generalizable = True``) renders from the source views it is given and is trained on
    many scenes; a **per-scene** family renders from its own parameters, fitted on one scene's frames (its
    ``predict`` gets ``sources=None``).

    Class attributes:
        generalizable: renders from source views.
        accepts_head: decodes a rendered feature map with the configured ``+head``; a family that only renders
            per-pixel scores (label rendering) sets False and refuses a configured head with a ConfigError.
        trains_on: ``TrainingBatch.RAYS`` (random pixels, the default) or ``TrainingBatch.IMAGES`` (whole target
            images: a rasterizing family, whose ``forward`` renders every pixel and may leave ``RenderedRays.weights``
            and ``samples`` None).
        source_encoding: what ``render``, ``view`` and ``export`` keep between frames (``SourceEncoding``): each
            source view's ``encode`` (the default), or the whole source set's ``encode_sources``.
        changes_size: its parameters are replaced by larger or smaller ones while it trains (3D Gaussian splatting's
            densification and pruning, through ``gpnerf_core.resize_parameter``); it then takes a checkpoint's sizes
            in ``resize_to``, and the trainer refuses what cannot follow a size change (a weight average, several
            processes).
    """

    generalizable: ClassVar[bool] = True
    accepts_head: ClassVar[bool] = True
    trains_on: ClassVar[TrainingBatch] = TrainingBatch.RAYS
    source_encoding: ClassVar[SourceEncoding] = SourceEncoding.PER_VIEW
    changes_size: ClassVar[bool] = False

    # ---- what the model is ------------------------------------------------------------------------------------------

    @property
    @abstractmethod
    def semantic_output(self) -> SemanticOutput | None:
        """What its semantic scores are, or None for a model that renders colour and depth only."""

    @abstractmethod
    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by learning-rate group; every trainable parameter in exactly one group (checked when the
        optimizer is built). A group's rate is ``model.lr.<group>``: the family's config has an ``lr`` section that
        declares every group named here with its default, the shared parts' (``feature_extractor``, ``head``) too."""

    def training_callbacks(self) -> Sequence[TrainingCallback]:
        """Work the training loop runs at fixed points of each step, told the step (``TrainingCallback``): a schedule
        tied to the step, or work between backward and the optimizer step. None by default."""
        return ()

    def optimizer_options(self, total_steps: int) -> Mapping[str, GroupOptions]:
        """By learning-rate group, where the family's optimizer differs from the run's (``GroupOptions``: its own rate
        schedule over ``total_steps`` (``train.steps``), Adam's epsilon). Read once, when the optimizer is built
        (after ``initialise``). None by default."""
        return {}

    def initialise(self, scene: Scene) -> None:
        """Called once on a per-scene family (``generalizable`` False) before its first training step, with the scene
        it is fitted on, unless the run resumes: a family whose parameters come from the scene's data (3D Gaussians
        from its sparse points or depth) makes them here, and one that holds weights already (``model.init``,
        ``finetune``) keeps them. A scene without what it needs is a ``DataError`` naming what is missing. Nothing by
        default."""

    def resize_to(self, weights: Mapping[str, Tensor], source: str) -> None:
        """Called before ``weights`` (a checkpoint's, ``model.init``'s) are loaded into the model: a family that
        ``changes_size`` gives its tensors the sizes the weights have (a checkpoint's Gaussian count), and refuses
        weights whose sizes disagree with each other in one line naming ``source``. Nothing by default (a tensor of
        another shape is then refused by the loader)."""

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per direct child module (absent ones left out) and their ``total``."""
        counts = {name: sum(p.numel() for p in module.parameters()) for name, module in self.named_children()}
        counts = {name: count for name, count in counts.items() if count}
        return {**counts, "total": sum(p.numel() for p in self.parameters())}

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        """Which part made each output of a ``Prediction`` (``colour``, ``depth``, ``semantic map``, ``logits``), for
        the message naming the part that gave NaN or Inf.

        Args:
            names: the configured component name of each kind (``{"model": "gnt", "head": "unet", ...}``).
        """
        model = f"model {names.get('model')!r}"
        return {"colour": model, "depth": model, "semantic map": model, "logits": model}

    def check_image_size(self, height: int, width: int) -> None:
        """Raise ``ConfigError`` (one line, naming the size and what is expected) when images of ``height`` x
        ``width`` cannot be rendered or encoded; called before training or evaluation starts. By default any size can."""

    # ---- training ---------------------------------------------------------------------------------------------------

    @abstractmethod
    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        """Render the chosen rays (``TargetView.pixels``) of every target view of ``batch``.

        Args:
            semantics: the loss set reads semantic outputs (``ViewOutput.logits``, ``RenderedRays.semantic``, ...).
            sample_semantics: it also reads per-sample semantic features (``RenderedRays.sample_semantic``).

        Returns:
            One ``ViewOutput`` per target view, in batch order. In training mode, randomness comes from a generator
            seeded with each view's ``render_seed`` (a view renders the same on any process); in eval mode none.
        """

    # ---- whole views ------------------------------------------------------------------------------------------------

    @abstractmethod
    def predict(
        self,
        camera: TargetCamera,
        sources: SourceViews | None,
        *,
        stride: int,
        chunk_rays: int,
        features: FeatureMaps | Any | None = None,
    ) -> Prediction:
        """Render a whole view (under inference mode) on a ``stride`` grid, ``chunk_rays`` rays at a time.

        Args:
            sources: its source views (None for a per-scene family).
            stride: pixels per rendered cell; 0 = the model's natural stride (the semantic map's, for GP-NeRF).
            features: what the caller kept of the sources: their ``encode`` maps (``SourceEncoding.PER_VIEW``) or the
                set's ``encode_sources`` (``SOURCE_SET``); None computes it.
        """

    def encode(self, images: Tensor) -> FeatureMaps:
        """Encoded maps of ``[N, 3, H, W]`` source images, which ``predict`` reuses when given them (kept between renders
        by ``model.feature_cache``; ``SourceEncoding.PER_VIEW``). A family without an encoder raises ConfigError."""
        raise ConfigError(f"model {type(self).__name__} encodes no source views")

    def encode_sources(self, sources: SourceViews, *, near: float, far: float) -> Any:
        """What a ``SourceEncoding.SOURCE_SET`` family computes from a whole set of source views and their scene's
        depth bounds (its Gaussians, say), which ``predict`` reuses when given it as ``features`` (kept between renders
        per set of source frames). Whatever it returns, its tensors are counted against the cache's budget. By
        default a family has none (ConfigError)."""
        raise ConfigError(f"model {type(self).__name__} encodes no source set (its source_encoding is "
                          f"{self.source_encoding.value})")

    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: Any = None) -> GaussianScene | None:
        """The 3D Gaussians the family renders from (``export`` writes them as the standard 3D Gaussian splatting PLY,
        ``view`` draws them as splats), each labelled with its class or instance slot; None for a family that renders
        no Gaussians (the default). A feed-forward family gives those it predicts from ``sources`` (``features``: what
        ``encode_sources`` gave for them, when the caller kept it); a per-scene one its own."""
        return None

    def teacher_logits(self, image: Tensor) -> Tensor | None:
        """The 2D-only reference: its head on the target image's own features, ``[3, H, W]`` -> ``[1, K, H, W]``; None
        when the family has no such reference (it is then not reported)."""
        return None

    # ---- options every family may have ------------------------------------------------------------------------------

    def use_compiled(self, backend: str | None) -> None:
        """Run the model's heavy parts ``torch.compile`` d with ``backend`` (None: eager). By default a family has no
        compiled path: asking for one is a ConfigError."""
        if backend is not None:
            raise ConfigError(f"model {type(self).__name__} has no compiled path (model.compile=true)")

    @contextlib.contextmanager
    def preview_sampling(self, depth_source: DepthSource, samples: int) -> Iterator[bool]:
        """While entered, ``predict`` renders with ``samples`` samples per ray placed by ``depth_source`` (one pass,
        no coarse pass; a family trained with a depth source of its own keeps it): the viewer's preview, cheap and
        approximate. Yields whether the family honours it; by default it does not (and renders as configured)."""
        yield False

    def read_foreign(self, checkpoint: Mapping[str, Any]) -> ImportedWeights | None:
        """The model's share of another code base's checkpoint (``model.init=<file>``, e.g. an official GNT one): the
        tensors by the model's own state-dict keys, the format's name, the checkpoint's weight keys it offers and its
        top-level entries left out on purpose. None: not a format this family reads."""
        return None
