"""Schema of the primary config: every key outside the component groups, typed and documented.

Stored in Hydra's ConfigStore as ``gpnerf_schema`` and listed first in ``conf/config.yaml``'s defaults, so a
misspelled key (``train.step=10``) fails at composition with the key named.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Optional

from omegaconf import MISSING

from gpnerf_core.registry.declarations import fewer, fractions, halved_or_none, size_knob


@dataclass
class ModelConfig:
    """The options every model family has: its config (``model=<name>``) subclasses this one.

    The core reads ``num_source_views``, ``init`` and ``init_strict`` itself, and the family's learning rates: the one
    home of every rate a run trains with is the family's ``lr`` section (a dataclass field ``lr`` whose fields are the
    groups its ``parameter_groups()`` names, the shared parts' ``feature_extractor`` and ``head`` included, with their
    defaults; ``model.lr.<group>=...``); the family's factory gets the others. The parts a family builds are fields of
    its config declared with ``gpnerf_core.part`` (``feature_extractor: Any = part("<default option>")``): the core
    mounts their config groups under ``model`` and keeps them from the factory, which builds them through
    ``ModelParts``. A ray-marching family's config subclasses ``RayMarchingConfig`` (its sample counts). Fields ``size``
    may turn down are declared with ``gpnerf_core.size_knob``.
    """

    name: str = ""
    """Registry name of the model family (each subclass defaults it to its own)."""
    num_source_views: int = size_knob(10, "source views", fewer(1, 2))
    """Source views per target (a generalizable family's; a per-scene family has none)."""
    init: Optional[str] = None
    """Start from these weights: a gpnerf-core checkpoint (its model weights only: the weight average where the run
    kept one) or another code base's checkpoint the family reads (an official GNT one for GP-NeRF's family). Ignored when
    resuming."""
    init_strict: bool = True
    """Refuse an init checkpoint holding keys no component maps (False: load the rest and list them)."""

    runtime_keys: ClassVar[tuple[str, ...]] = ("init", "init_strict", "lr", "loss_weights")
    """Fields that change how weights start or train, or how time and memory are spent, not the model: resuming or
    evaluating with other values is allowed (a family's config adds its own)."""


@dataclass
class RayMarchingConfig(ModelConfig):
    """The options of a family that samples points along rays (GNT, NeuRay, MVSNeRF, Semantic-NeRF, ...): its sample
    counts, which the core validates, ``size`` tries and ``bench`` reports for such a family only."""

    coarse_samples: int = size_knob(48, "coarse samples", fractions(2, 4, 0.75, 0.5))
    """Stratified samples per ray (inverse-depth spacing)."""
    fine_samples: int = size_knob(16, "fine samples", halved_or_none)
    """Importance samples added for the fine pass (0 = single pass)."""


@dataclass
class TrainConfig:
    steps: int = 200_000
    """Optimizer steps (one target view each)."""
    rays: int = 512
    """Rays per target view per step (a step renders ``rays x targets_per_step`` rays over all processes)."""
    targets_per_step: int = 1
    """Target views per step over all processes (the global batch; the paper: 1 per GPU). Under torchrun the
    world size must divide it; each process takes its share."""
    lr_schedule: str = "exponential"
    """After the warm-up: ``exponential`` (multiplied by ``lr_decay_rate`` every ``lr_decay_steps`` steps, per step)
    or ``cosine`` (half a cosine from the full rate down to 0 at ``train.steps``)."""
    lr_decay_rate: float = 0.6
    """``exponential``: learning rates are multiplied by this factor every ``lr_decay_steps`` steps."""
    lr_decay_steps: int = 100_000
    """``exponential``: steps per ``lr_decay_rate`` factor."""
    warmup_steps: int = 0
    """Learning rates rise linearly from 1/warmup_steps of their value to the full value over these first steps
    (0 = none)."""
    grad_clip: float = 0.0
    """Clip the global gradient norm to this value (0 = off). The training curves log the unclipped norm."""
    ema_decay: float = 0.0
    """Keep an exponential moving average of the weights with this decay (0 = off; e.g. 0.99 averages over about
    the last 100 steps) and evaluate it instead of the last step's weights; checkpoints hold both."""
    log_every: int = 10
    """Steps between entries of the training curves."""
    checkpoint_every: int = 0
    """Steps between checkpoints (0 = only the final one)."""
    keep_checkpoints: int = 0
    """Keep only the newest K checkpoints of the run folder, deleting older ones as new ones are written (0 = keep
    all)."""
    resume: Optional[str] = None
    """Checkpoint to resume from (restores model, optimizer, step and random state), or ``auto``: the newest intact
    checkpoint in ``out_dir`` if there is one, else a fresh start (what a restarted or requeued job runs)."""
    resume_strict: bool = True
    """Refuse to resume when the model or loss config differs from the checkpoint's (False: print the
    differences and go on)."""
    precision: str = "fp32"
    """``fp32``, or ``bf16``: the forward pass and the losses under bfloat16 autocast (CPU and CUDA); weights,
    gradients and the optimizer stay float32."""
    loggers: list[str] = field(default_factory=lambda: ["csv"])
    """Where training scalars and evaluation metrics also go: ``csv`` (``scalars.csv`` in the run folder) and/or
    ``tensorboard`` (``tensorboard/`` event files; needs the ``tensorboard`` extra). Rank 0 only."""


@dataclass
class EvalConfig:
    render_stride: int = 0
    """Stride of the rendered grid; 0 = the semantic map's stride (2 for GP-NeRF), so the head sees a full map."""
    chunk_rays: int = 2048
    """Rays rendered at once (bounds memory)."""
    max_views_per_scene: int = 0
    """Cap on held-out targets per scene (0 = all)."""
    save_images: int = 2
    """Targets per split whose pictures are written."""
    splits: list[str] = field(default_factory=lambda: ["train", "unseen"])
    """Which scene splits to evaluate: held-out views of ``train`` scenes, and ``unseen`` scenes."""
    weights: str = "average"
    """Which weights of a checkpoint ``eval``, ``render`` and ``finetune`` start from: ``average`` (the run's
    weight average, ``train.ema_decay``, where it kept one; else the trained weights) or ``trained``."""
    every_steps: int = 0
    """``run``: also evaluate every this many training steps (0 = only at the end); ``metrics.json`` gets
    ``eval_curve``, accuracy against steps and training seconds, which ``report --chart`` draws."""
    query_protocol: bool = False
    """Also score the query protocol (``query/nearest_prototype``, docs/features.md): nearest-prototype segmentation
    of the held-out frames from ``prototype_frames`` labelled training frames per class, per feature source, beside
    the class head's mIoU. It renders those training frames too."""
    prototype_frames: int = 1
    """The query protocol's labelled training frames per class (drawn by ``seed``), an integer >= 1."""


@dataclass
class FinetuneConfig:
    points: int = 4
    """``finetune``: evaluate the held-out frames at this many step counts from 0 to ``train.steps`` (0, N/3, 2N/3, N
    for 4)."""


@dataclass
class FitConfig:
    """``fit``: one scene's per-scene Gaussian model fitted until it has enough (docs/fit.md). The step budget is
    ``train.steps``."""

    eval_every: int = 100
    """Training steps between evaluations of the held-out frames, the curve's points (also evaluated at step 0, the
    start, and at the last step); 0 = only at the start and the end (then no ``target`` nor ``patience``)."""
    seconds: Optional[float] = None
    """Training-seconds budget: the fit stops after the first step that reaches it (null = none; 0 or less is
    refused). Wall time: a stop by it is not reproducible step for step."""
    target: Optional[float] = None
    """Stop at the first evaluation whose ``metric`` on the held-out frames reaches this value (null = none)."""
    metric: str = "miou/image_mean_present"
    """The held-out metric ``target`` and ``patience`` read (a key the evaluation gives the split ``train_heldout``;
    a scene without labels: ``psnr/clamped``). ``depth/*`` and ``lpips/*`` are lower-is-better, the others higher."""
    patience: int = 0
    """Plateau: stop after this many evaluations in a row without a gain of at least ``min_delta`` over the best so
    far (0 = no plateau rule)."""
    min_delta: float = 0.005
    """The smallest gain of ``metric`` that counts as an improvement for ``patience`` (in the metric's units)."""
    start_every: int = 1
    """A checkpoint start: every ``start_every``-th training frame of the scene gives the start's Gaussians."""
    start_opacity: float = 0.8
    """A checkpoint start from a ray family: the opacity of each rendered cell's Gaussian, in (0, 1) (a feed-forward
    Gaussian family predicts its own; ``generalized_start.START_OPACITY`` says why 0.8)."""
    start_budget: int = 0
    """A checkpoint start keeps at most this many Gaussians, the most opaque (0 = ``model.max_gaussians``): below the
    budget, density control has room to grow where the start is thin."""
    start_min_views: int = 1
    """A checkpoint start's depth-map fusion: a frame's Gaussian stays where at least this many other frames' predicted
    depth agrees with it within ``start_tolerance`` (0 = no agreement needed)."""
    start_conflicts: int = 3
    """... and where at most this many other frames see through it (their predicted surface behind it: a floater)."""
    start_tolerance: float = 0.1
    """Relative depth tolerance of that agreement and of seeing through."""
    start_geometry: str = "predicted"
    """A checkpoint start's Gaussians: "predicted" (the model's predicted Gaussians or rendered depth, fused as above)
    or "points" (the scene's own points, as a fit without a checkpoint starts, each given the model's semantics where
    it falls in the training frames: for a model whose labels hold where its depth does not)."""
    start_semantics: bool = True
    """Whether the start's semantics (its features with the generalizable model's head, or its class scores) begin the
    per-scene decoder; false keeps only its geometry and colour, the decoder and features starting as from points."""


@dataclass
class RenderConfig:
    scene: str = ""
    """``render``: the scene to render ("" = the first unseen scene, else the first training scene; a per-scene model's
    own scene, the only one it renders)."""
    path: str = "interpolate"
    """``interpolate`` (through the held-out frames' poses) or ``spiral`` (around frame ``frame``)."""
    frames: int = 30
    """Poses on the trajectory."""
    frame: int = 0
    """``spiral``: the frame whose pose is the centre."""
    radius: float = 0.1
    """``spiral``: radius of the circle, metres."""
    focus: float = 2.0
    """``spiral``: distance to the point looked at, metres."""
    fps: int = 10
    """Frames per second of the MP4 and GIF, an integer in [1, 50] (``render`` checks it)."""
    feature_cache_mb: float = 512.0
    """Encoded source features kept between frames of the trajectory (``feature_cache``), megabytes; 0 = encode the
    sources of every frame again."""


@dataclass
class ExportQueryConfig:
    """``export.query``: a query by example written as its own PLY files (off unless ``pixel`` or ``box`` is given)."""

    pixel: list[float] = field(default_factory=list)
    """``[x, y]``: the example pixel (full-image pixel coordinates, x right, y down) in frame ``frame``."""
    box: list[float] = field(default_factory=list)
    """``[x0, y0, x1, y1]``: the example box (corners included) in frame ``frame``, instead of ``pixel``."""
    frame: int = -1
    """The scene frame the example is in, rendered at its own camera (-1 = the first exported frame)."""
    threshold: float = 0.8
    """Cosine relevancy in [-1, 1] from which a Gaussian or a point is selected."""


@dataclass
class ExportConfig:
    scene: str = ""
    """``export``: the scene to export ("" = the first unseen scene, else the first training scene; a per-scene model's
    own scene, the only one it renders)."""
    frames: str = "eval"
    """Which of the scene's frames are rendered at their cameras: ``eval`` (held-out), ``train`` or ``all``; each
    takes its source views from the training frames but itself."""
    every: int = 1
    """Every ``every``-th of those frames, from the first."""
    stride: int = 0
    """Pixels per rendered cell (one point per cell); 0 = ``eval.render_stride``."""
    min_views: int = 1
    """A point is kept where at least this many of the other exported views rendered a surface at its depth
    (``tolerance``); 0 keeps every point inside the scene's depth bounds."""
    tolerance: float = 0.05
    """Relative depth difference under which another view agrees with a point (0.05 = 5 %; another view's depth is
    read at its nearest rendered cell, so a slanted surface differs by a cell's footprint there)."""
    voxel: float = 0.0
    """Merge the points of each cube of this side, metres (mean position and colour, most frequent label); 0 = none."""
    query: ExportQueryConfig = field(default_factory=ExportQueryConfig)
    """A query by example: the Gaussians and points similar to it as ``selection_gaussians.ply`` and
    ``selection_points.ply`` (docs/features.md, "Queries")."""


@dataclass
class LabelConfig:
    scene: str = ""
    """``label``: the scene whose frames are labelled ("" = the first unseen scene, else the first training scene)."""


@dataclass
class ViewConfig:
    port: int = 8080
    """``view``: TCP port of the web viewer (0 = any free port; a port in use is refused)."""
    host: str = "127.0.0.1"
    """``view``: address the viewer listens on (the default reaches this machine only; 0.0.0.0 = every interface)."""
    scene: str = ""
    """``view``: the scene shown first ("" = the first unseen scene, else the first training scene; a per-scene model's
    own scene, the only one it shows)."""
    stride: int = 2
    """``view``: pixels per rendered cell of the full frame, rendered once the camera rests."""
    preview_stride: int = 8
    """``view``: pixels per rendered cell of the coarse preview shown first while the camera moves."""
    preview_samples: int = 8
    """``view``: samples per ray of the preview, placed around each ray's depth from ``preview_depth_source`` in one
    pass (a family that cannot, renders the preview as the full frame); 0 = the preview samples as the full frame."""
    preview_depth_source: str = "cost_volume"
    """``view``: the depth source (``+depth_source`` names) that places the preview's samples, unless the model was
    trained with one of its own."""
    source_views: int = 0
    """``view``: source views per rendered view (0 = ``model.num_source_views``); the viewer's slider changes it."""
    feature_cache_mb: float = 256.0
    """``view``: megabytes of encoded source feature maps kept, so a moving camera encodes only new sources (0 = off)."""


@dataclass
class FeaturesConfig:
    """Feature fields (docs/features.md, "Feature fields"): with ``+feature_provider=<name>`` a family that renders a
    feature field distils the provider's 2D features of its training frames into it. Read only with a provider."""

    loss: str = "cosine"
    """The distillation term: ``cosine`` (1 - cosine similarity per provider cell or ray) or ``l1`` (mean absolute
    difference per channel)."""
    weight: float = 1.0
    """Weight of the term (logged as ``train/feature_field``); 0 renders the field without training it."""
    channels: int = 16
    """At most this many channels per Gaussian (0 to 16; 0 = the provider's own, uncompressed): a provider with more
    is compressed per scene by an autoencoder fitted on its training frames' features before the field trains
    (LangSplat), and the field decoded back to the provider's channels."""
    autoencoder_steps: int = 1000
    """Adam steps of that autoencoder's fit."""
    autoencoder_hidden: int = 128
    """Hidden width of its encoder and decoder (one hidden layer each)."""
    autoencoder_lr: float = 2e-3
    """Adam's learning rate of its fit."""
    autoencoder_samples: int = 65536
    """At most this many feature vectors (provider cells of the training frames, drawn at random) fit it."""


@dataclass
class RootConfig:
    model: Any = MISSING
    """The model family (``model=<name>``; ``ModelConfig`` and the family's own options), with the parts it builds
    mounted under it (``model.feature_extractor``, ``model.field_aggregator``, ...: ``model/<kind>=<name>``)."""
    dataset: Any = MISSING
    view_selector: Any = MISSING
    head: Any = None
    """Add-on group: ``+head=<name>``."""
    loss: Any = None
    """Add-on group: ``+loss=<name>``."""
    depth_source: Any = None
    """Add-on group: ``+depth_source=<name>``: where ``model.sampler=depth`` takes each ray's cheap depth from (none:
    the family's own first pass)."""
    feature_provider: Any = None
    """Add-on group: ``+feature_provider=<name>``: the frozen 2D model whose per-frame features a feature field distils
    and queries compare against (``gpnerf_core.features``; none: no feature field)."""
    seed: int = 0
    device: str = "auto"
    """``auto`` (CUDA when available), ``cpu`` or ``cuda[:N]``."""
    threads: int = 0
    """CPU threads for torch (0 = torch's default)."""
    keep_freed_memory: bool = True
    """Large CPU tensors reuse memory the process already holds instead of page-faulting fresh pages in (glibc malloc
    tuned by ``gpnerf_core.runtime.host_memory``: a paper-size frame's system time 74 s -> 5 s); resident memory then
    stays at its peak. False: glibc's defaults."""
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    view: ViewConfig = field(default_factory=ViewConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    label: LabelConfig = field(default_factory=LabelConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    """Feature fields (read only with ``+feature_provider=<name>``)."""
    out_dir: str = ""
    """Run folder; empty = Hydra's output directory. Nothing is written under ``outputs/`` when it is set."""
    overwrite: bool = False
    """Replace the run a non-empty ``out_dir`` holds (its checkpoints, metrics and pictures are deleted)."""
    checkpoint: Optional[str] = None
    """Checkpoint the ``eval`` command evaluates, ``finetune`` starts from and ``render`` renders; ``fit``: the
    generalizable run whose prediction starts the per-scene model (none: the scene's points)."""
