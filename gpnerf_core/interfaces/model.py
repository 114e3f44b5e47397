"""Interface of model families: what renders a target view (its rays, or whole images), and the only thing every tool
drives.

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
from gpnerf_core.interfaces.training import GroupOptions, TrainingCallback, TrainingState
from gpnerf_core.interfaces.weights import ImportedWeights
from gpnerf_core.types import FeatureMaps, Prediction, Scene, SourceViews, StepBatch, StepOutput, TargetCamera

if TYPE_CHECKING:
    from gpnerf_core.geometry.gaussians.scene import GaussianScene


class TrainingBatch(str, enum.Enum):
    """What one target view of a training step is: what the family renders and the loss compares."""

    RAYS = "rays"
    """``train.rays`` pixels drawn at random (a ray-marching family: each ray costs its samples)."""
    IMAGES = "images"
    """Whole target images (``TargetView.whole_image``, no pixels drawn): a family that renders whole images at once
    (rasterized Gaussians) returns an ``ImageOutput`` per view, and its loss set reads images (``ImageLossInputs``:
    image terms such as SSIM, a validity mask)."""


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

    def feature_field(self) -> Any | None:
        """The configured feature provider as a feature field (``gpnerf_core.features.field.FeatureField``: its
        channels and grid, the channels to carry, its maps of any frame), or None without ``+feature_provider``. Called
        by a family that declares ``Capabilities.feature_field``."""
        return None

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


class FamilyHooks:
    """What a model family may ask of the training loop besides its forward pass, on one optional object (nerfstudio's
    ``get_training_callbacks`` and ``get_loss_dict``, gsplat's strategy calls): every member has a default that does
    nothing. A family names its subclass in ``Capabilities.hooks``; the trainer and the tools reach it as
    ``model.hooks`` (made once per model, with the model as ``self.family``). Whatever a hook needs from a training
    step it is given (``TrainingState``: the step, the optimizer, the step's outputs), never through the family's own
    attributes.

    A capability the family declares (``Capabilities``) must be implemented here or on the family, and a member
    implemented must be declared: the registry refuses a family that does one without the other, naming its plugin.
    """

    def __init__(self, family: "ModelFamily") -> None:
        self.family = family

    def callbacks(self) -> Sequence[TrainingCallback]:
        """Work the training loop runs at fixed points of each step, told the step and its outputs
        (``TrainingCallback``, ``TrainingState``): a schedule tied to the step, densification between backward and
        the optimizer step. None by default."""
        return ()

    def optimizer_options(self, total_steps: int) -> Mapping[str, GroupOptions]:
        """By learning-rate group, where the family's optimizer differs from the run's (``GroupOptions``: its own rate
        schedule over ``total_steps`` (``train.steps``), Adam's epsilon). Read when the optimizer is built (after
        ``initialise``, and again when a family that ``changes_size`` resumes). None by default."""
        return {}

    def initialise(self, scene: Scene) -> None:
        """Called once on a per-scene family (``generalizable`` False) before its first training step, with the scene
        it is fitted on, unless the run resumes: a family whose parameters come from the scene's data (3D Gaussians
        from its sparse points or depth) makes them here, and one that holds weights already (``model.init``,
        ``finetune``) keeps them. A scene without what it needs is a ``DataError`` naming what is missing."""

    def resize_to(self, weights: Mapping[str, Tensor], source: str) -> None:
        """Called before ``weights`` (a checkpoint's, ``model.init``'s) are loaded into a family that ``changes_size``:
        its tensors take the sizes the weights have (a checkpoint's Gaussian count); weights whose sizes disagree
        with each other are refused in one line naming ``source``. Required with ``Capabilities.changes_size``."""

    def check_weights(self, weights: Mapping[str, Tensor], source: str) -> None:
        """Called before ``weights`` (a checkpoint's, ``model.init``'s) are loaded, before their keys are compared
        with the model's: a family whose structure changed refuses weights of an older structure here in one line
        naming ``source`` and the fix (``DataError``), rather than as a list of missing tensors. Nothing by default."""

    def loss_terms(self, state: TrainingState, wanted: frozenset[str]) -> Mapping[str, Tensor]:
        """The family's own loss terms of this step, unweighted scalars by name, computed on its own state (its
        Gaussians, its fields) and the step's outputs (``state.batch``, ``state.outputs``): a 3D regulariser, a scale
        or opacity penalty. Every name in ``wanted`` (the names of ``Capabilities.loss_terms`` whose
        ``model.loss_weights.<name>`` is not 0; others need not be computed) each step, a term not due this step as a
        zero. The trainer weights each, adds them to the loss set's terms, logs them as ``train/<name>`` and stops on
        NaN or Inf naming the family and the term. Required with ``Capabilities.loss_terms``."""
        return {}

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        """Which part made each output of a ``Prediction`` (``colour``, ``depth``, ``semantic map``, ``logits``), for
        the message naming the part that gave NaN or Inf: the model, and the head for ``logits`` when the family built
        one (``parts.head``) .

        Args:
            names: the configured component name of each kind (``{"model": "gnt", "head": "unet", ...}``).
        """
        model = f"model {names.get('model')!r}"
        owners = {"colour": model, "depth": model, "semantic map": model, "logits": model}
        if getattr(self.family, "head", None) is not None and names.get("head") is not None:
            owners["logits"] = f"head {names.get('head')!r}"
        return owners

    def use_compiled(self, backend: str | None) -> None:
        """Run the model's heavy parts ``torch.compile`` d with ``backend`` (None: eager). Required with
        ``Capabilities.compiled``; without it, asking for a compiled path is a ConfigError."""
        if backend is not None:
            raise ConfigError(f"model {type(self.family).__name__} has no compiled path (model.compile=true)")


@dataclass(frozen=True)
class Capabilities:
    """What a model family is and offers, in one record: every tool reads it instead of probing the family.

    Attributes:
        generalizable: renders from the source views it is given, trained on many scenes; False: a per-scene family
            that renders from its own parameters (training views carry no sources, ``predict`` gets None).
        accepts_head: decodes a rendered feature map with the configured ``+head``; a family that only renders
            per-pixel scores (label rendering) says False and refuses a configured head with a ConfigError.
        trains_on: ``TrainingBatch.RAYS`` (random pixels; ``forward`` returns ``ViewOutput`` s) or
            ``TrainingBatch.IMAGES`` (whole target images; ``forward`` returns ``ImageOutput`` s).
        source_encoding: what ``render`` and ``view`` keep between frames (``SourceEncoding``): each
            source view's ``encode`` or the whole set's ``encode_sources``; None for a per-scene family.
        changes_size: its parameters are replaced by larger or smaller ones while it trains (densification, through
            ``gpnerf_core.resize_parameter``): ``hooks.resize_to`` gives it a checkpoint's sizes, and the trainer refuses
            what cannot follow a size change (a weight average, several processes).
        gaussians: it renders from 3D Gaussians it can give (``scene_gaussians``): ``export`` writes them, ``view``
            draws them.
        teacher: it has a 2D-only reference (``teacher_logits``), reported beside its own scores.
        preview: it can render a cheap preview for the viewer (``preview_sampling``).
        compiled: it has a ``torch.compile`` d path (``hooks.use_compiled``).
        foreign_weights: it reads another code base's checkpoints (``read_foreign``, ``model.init=<file>``).
        loss_terms: the names of its own loss terms (``hooks.loss_terms``), each weighted by
            ``model.loss_weights.<name>``.
        hooks: its ``FamilyHooks`` subclass (the default does nothing).
        segments_image: a 2D model, not a renderer: ``predict`` segments the target's real image
            (``TargetCamera.image``), which evaluation gives it and nothing else does; it renders no colour or depth
            (evaluation scores none) and no novel pose (``render``, ``view`` refuse it). A per-scene 2D baseline (Mask
            R-CNN) says True: its scores are a 2D segmenter's on the true image, like ``teacher_2d``, never a rendering.
        feature_field: it renders a feature field distilled from a feature provider (``+feature_provider=<name>``):
            built through ``parts.feature_field()``, rendered as ``ImageOutput.features`` / ``RenderedRays.features``
            in training and ``Prediction.features`` in evaluation (docs/features.md, "Feature fields"); a family
            without it refuses a configured provider in one line.
    """

    generalizable: bool = True
    accepts_head: bool = True
    trains_on: TrainingBatch = TrainingBatch.RAYS
    source_encoding: SourceEncoding | None = SourceEncoding.PER_VIEW
    changes_size: bool = False
    gaussians: bool = False
    teacher: bool = False
    preview: bool = False
    compiled: bool = False
    foreign_weights: bool = False
    loss_terms: tuple[str, ...] = ()
    hooks: type[FamilyHooks] = FamilyHooks
    segments_image: bool = False
    feature_field: bool = False


class ModelFamily(nn.Module, ABC):
    """Renders colour, depth and semantics of a target view; trained, evaluated, rendered and viewed unchanged.

    Built by its factory with its config fields (a subclass of ``gpnerf_core.ModelConfig``) and ``parts``
    (``ModelParts``). The core reads ``model.num_source_views``, ``model.init``, ``model.init_strict``,
    ``model.lr`` and ``model.loss_weights`` itself; every other field goes to the factory.

    What the family is and offers is one class attribute, ``capabilities`` (``Capabilities``); what it asks of the
    training loop is one object, ``hooks`` (``FamilyHooks``). Twelve members besides: what it renders
    (``semantic_output``, ``parameter_groups``), training (``forward``), whole views (``predict``, ``encode``,
    ``encode_sources``, ``scene_gaussians``, ``teacher_logits``, ``preview_sampling``) and its inputs
    (``check_image_size``, ``read_foreign``). Parameter counts are ``gpnerf_core.parameter_counts(model)``.
    """

    capabilities: ClassVar[Capabilities] = Capabilities()

    @property
    def hooks(self) -> FamilyHooks:
        """The family's ``FamilyHooks`` (``capabilities.hooks``), made once and kept."""
        made = self.__dict__.get("_family_hooks")
        if made is None or made.family is not self:
            made = type(self).capabilities.hooks(self)
            self.__dict__["_family_hooks"] = made
        return made

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

    def check_image_size(self, height: int, width: int) -> None:
        """Raise ``ConfigError`` (one line, naming the size and what is expected) when images of ``height`` x
        ``width`` cannot be rendered or encoded; called before training or evaluation starts. By default any size can."""

    def read_foreign(self, checkpoint: Mapping[str, Any]) -> ImportedWeights | None:
        """The model's share of another code base's checkpoint (``model.init=<file>``, e.g. an official GNT one): the
        tensors by the model's own state-dict keys, the format's name, the checkpoint's weight keys it offers and its
        top-level entries left out on purpose. None: not a format this family reads. With
        ``Capabilities.foreign_weights``."""
        return None

    # ---- training ---------------------------------------------------------------------------------------------------

    @abstractmethod
    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        """Render every target view of ``batch``: the chosen rays (``TargetView.pixels``) of a ray family, each
        whole image of one that trains on images.

        Args:
            semantics: the loss set reads semantic outputs (``ViewOutput.logits``, ``RenderedRays.semantic``,
                ``ImageOutput.scores``, ...).
            sample_semantics: it also reads per-sample semantic features (``RenderedRays.sample_semantic``).

        Returns:
            One ``ViewOutput`` (``TrainingBatch.RAYS``) or ``ImageOutput`` (``TrainingBatch.IMAGES``) per target view,
            in batch order. In training mode, randomness comes from a generator seeded with each view's
            ``render_seed`` (a view renders the same on any process); in eval mode none.
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
        """Render a whole view (under inference mode) on a ``stride`` grid.

        Args:
            sources: its source views (None for a per-scene family).
            stride: pixels per rendered cell; 0 = the model's natural stride (the semantic map's, for GP-NeRF).
            chunk_rays: rays rendered at once by a ray family (bounds memory); a family that renders whole images
                renders a view in one call and ignores it.
            features: what the caller kept of the sources: their ``encode`` maps (``SourceEncoding.PER_VIEW``) or the
                set's ``encode_sources`` (``SOURCE_SET``); None computes it.
        """

    def encode(self, images: Tensor) -> FeatureMaps:
        """Encoded maps of ``[N, 3, H, W]`` source images, which ``predict`` reuses when given them (kept between renders
        by ``model.feature_cache``): ``SourceEncoding.PER_VIEW``."""
        raise ConfigError(f"model {type(self).__name__} encodes no source views one by one")

    def encode_sources(self, sources: SourceViews, *, near: float, far: float) -> Any:
        """What a ``SourceEncoding.SOURCE_SET`` family computes from a whole set of source views and their scene's
        depth bounds (its Gaussians, say), which ``predict`` reuses when given it as ``features`` (kept between renders
        per set of source frames). Whatever it returns, its tensors are counted against the cache's budget."""
        raise ConfigError(f"model {type(self).__name__} encodes no source set")

    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: Any = None) -> GaussianScene:
        """The 3D Gaussians the family renders from (``export`` writes them as the standard 3D Gaussian splatting PLY,
        ``view`` draws them as splats), each labelled with its class or instance slot (-1: none): a feed-forward
        family's predicted from ``sources`` (``features``: what ``encode_sources`` gave for them, when the caller kept
        it), a per-scene one's own. With ``Capabilities.gaussians``."""
        raise ConfigError(f"model {type(self).__name__} renders no Gaussians")

    def teacher_logits(self, image: Tensor) -> Tensor | None:
        """The 2D-only reference: its head on the target image's own features, ``[3, H, W]`` -> ``[1, K, H, W]``; None
        when the model as configured has none (no head). With ``Capabilities.teacher``."""
        return None

    @contextlib.contextmanager
    def preview_sampling(self, depth_source: DepthSource, samples: int) -> Iterator[bool]:
        """While entered, ``predict`` renders with ``samples`` samples per ray placed by ``depth_source`` (one pass,
        no coarse pass; a family trained with a depth source of its own keeps it): the viewer's preview, cheap and
        approximate. Yields whether the family honours it (``Capabilities.preview``)."""
        yield False


OPTIONAL_MEMBERS: dict[str, tuple[str, str]] = {
    "changes_size": ("hooks", "resize_to"),
    "gaussians": ("family", "scene_gaussians"),
    "teacher": ("family", "teacher_logits"),
    "preview": ("family", "preview_sampling"),
    "compiled": ("hooks", "use_compiled"),
    "foreign_weights": ("family", "read_foreign"),
    "loss_terms": ("hooks", "loss_terms"),
}
"""Capability -> where its member lives (the family class or its hooks class) and the member's name."""


def _overrides(cls: type, base: type, member: str) -> bool:
    return getattr(cls, member, None) is not getattr(base, member, None)


def capability_problems(family: type) -> list[str]:
    """What is wrong with a family class's ``capabilities``: each a line naming the capability and the member (a
    capability declared but not implemented, a member implemented but not declared, a value of the wrong type); empty
    when the record holds. The registry refuses a family with any (``gpnerf_register_models``)."""
    caps = getattr(family, "capabilities", None)
    name = family.__name__
    if not isinstance(caps, Capabilities):
        return [f"{name}.capabilities is {type(caps).__name__}, expected gpnerf_core.Capabilities"]
    problems = []
    hooks = caps.hooks
    if not (isinstance(hooks, type) and issubclass(hooks, FamilyHooks)):
        return [f"{name}.capabilities.hooks is {hooks!r}, expected a subclass of gpnerf_core.FamilyHooks"]
    for flag in ("generalizable", "accepts_head", "changes_size", "gaussians", "teacher", "preview", "compiled",
                 "foreign_weights", "segments_image", "feature_field"):
        if not isinstance(getattr(caps, flag), bool):
            problems.append(f"{name}.capabilities.{flag} is {getattr(caps, flag)!r}, expected True or False")
    if not isinstance(caps.trains_on, TrainingBatch):
        problems.append(f"{name}.capabilities.trains_on is {caps.trains_on!r}, expected a TrainingBatch member")
    if caps.source_encoding is not None and not isinstance(caps.source_encoding, SourceEncoding):
        problems.append(f"{name}.capabilities.source_encoding is {caps.source_encoding!r}, expected a SourceEncoding "
                        "member or None")
    if caps.generalizable and caps.source_encoding is None:
        problems.append(f"{name} is generalizable but capabilities.source_encoding is None: a family that renders from "
                        "source views encodes them (SourceEncoding.PER_VIEW or SOURCE_SET)")
    if caps.segments_image and caps.generalizable:
        problems.append(f"{name} segments images (capabilities.segments_image) but is generalizable: a 2D model is "
                        "fitted per scene and reads no source views (generalizable=False)")
    if not caps.generalizable and caps.source_encoding is not None:
        problems.append(f"{name} is per-scene (generalizable=False) but capabilities.source_encoding is "
                        f"{caps.source_encoding.value}: it encodes no sources (source_encoding=None)")
    terms = caps.loss_terms
    if not isinstance(terms, tuple) or not all(isinstance(t, str) and t.isidentifier() for t in terms) \
            or len(set(terms)) != len(terms):
        problems.append(f"{name}.capabilities.loss_terms is {terms!r}, expected a tuple of distinct identifiers")
    for flag, (owner, member) in OPTIONAL_MEMBERS.items():
        cls, base = (family, ModelFamily) if owner == "family" else (hooks, FamilyHooks)
        declared, implemented = bool(getattr(caps, flag)), _overrides(cls, base, member)
        where = name if owner == "family" else f"its hooks {hooks.__name__}"
        if declared and not implemented:
            problems.append(f"{name} declares capabilities.{flag} but {where} does not implement {member}")
        elif implemented and not declared:
            problems.append(f"{where} implements {member} but {name} does not declare capabilities.{flag}")
    for encoding, member in ((SourceEncoding.PER_VIEW, "encode"), (SourceEncoding.SOURCE_SET, "encode_sources")):
        implemented = _overrides(family, ModelFamily, member)
        if caps.source_encoding is encoding and not implemented:
            problems.append(f"{name} declares capabilities.source_encoding={encoding.value} but does not implement "
                            f"{member}")
    return problems


def parameter_counts(model: nn.Module) -> dict[str, int]:
    """Parameters per direct child module of ``model`` (those without any left out) and their ``total``."""
    counts = {name: sum(p.numel() for p in module.parameters()) for name, module in model.named_children()}
    counts = {name: count for name, count in counts.items() if count}
    return {**counts, "total": sum(p.numel() for p in model.parameters())}
