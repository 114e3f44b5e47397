"""The body every per-scene Gaussian family shares (``GaussianFamily`` and its ``GaussianHooks``), built on the public
Gaussian strategy (``gpnerf_core.geometry.gaussians``): the Gaussians with the family's own channels, their start from
the scene's points, one rasterization per view, and the training loop's part in 3D Gaussian splatting (Kerbl et al.,
SIGGRAPH 2023; ``graphdeco-inria/gaussian-splatting``): Adam's epsilon and the centres' decaying rate, the colour's
degree raised on schedule, density control between backward and the optimizer step, a checkpoint's sizes.

A family subclasses both: it declares its channels (``channels``), its learning-rate group per Gaussian row
(``row_groups``), decodes what ``render`` gives (``forward``, ``predict``), labels its Gaussians
(``scene_gaussians``), and adds its own loss terms or callbacks on its hooks. ``semantic_3dgs`` and the Gaussian
Grouping example (``examples/gpnerf-gaussian-grouping``) are two.
"""

from __future__ import annotations

import math
import sys
from typing import Any, ClassVar, Mapping, Sequence

import torch
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError, DataError, NonFiniteError
from gpnerf_core.features.field import at_pixels
from gpnerf_core.geometry.projection import project_points
from gpnerf_core.geometry.gaussians.density import ViewInfo, scaled_step
from gpnerf_core.geometry.gaussians.harmonics import colour_to_dc, sh_colours
from gpnerf_core.geometry.gaussians.initialisation import neighbour_scales, scene_extent, starting_points
from gpnerf_core.geometry.gaussians.parameters import GaussianParameters, rows_from_points
from gpnerf_core.geometry.gaussians.rasterizer import rasterize_gaussians, strided_camera
from gpnerf_core.interfaces.head import PerceptionHead
from gpnerf_core.interfaces.model import Capabilities, FamilyHooks, ModelFamily, TrainingBatch
from gpnerf_core.interfaces.training import GroupOptions, TrainingCallback, TrainingPhase, TrainingState
from gpnerf_core.model.gaussian_config import GaussianSetup
from gpnerf_core.runtime.finite import all_finite
from gpnerf_core.types import ImageOutput, Scene, TargetCamera

ADAM_EPS = 1e-15
"""Adam's epsilon for the Gaussians' parameters (3DGS's ``training_setup``)."""
BASE_ROWS: dict[str, str] = {
    "means": "means",
    "harmonics_dc": "harmonics",
    "harmonics_rest": "harmonics_rest",
    "opacity_logits": "opacities",
    "log_scales": "scales",
    "rotations": "rotations",
}
"""3DGS's per-Gaussian parameters -> their learning-rate groups (``model.lr.<group>``); a family's channels add theirs
(``GaussianFamily.row_groups``)."""
INFO = "raster"
"""``ImageOutput.extras`` key of what the rasterizer reported of a training view (``ViewInfo``)."""
FIELD_CHANNEL = "feature_field"
"""The per-Gaussian channel of a feature field (``+feature_provider``): the provider's channels, or the autoencoder's
codes where they are compressed; its learning-rate group has the same name (``model.lr.feature_field``)."""


def rasterized(state: TrainingState) -> list[ViewInfo]:
    """What the rasterizer reported of each target view of the step (``ImageOutput.extras[INFO]``)."""
    return [view.extras[INFO] for view in state.outputs.views if INFO in view.extras]


class GaussianHooks(FamilyHooks):
    """A per-scene Gaussian family's start, optimizer options, checkpoint sizes and step schedule."""

    family: "GaussianFamily"

    def initialise(self, scene: Scene) -> None:
        """The Gaussians from the scene's points (``starting_points``): colour from the points, isotropic scales from
        the three nearest, opacity ``init_opacity``, each channel uniform as Gaussian Grouping's identities
        (``RGB2SH(U(0, 1))``); from ``family.start`` instead when one is set (``initialise_from_start``); unless
        weights were loaded already."""
        family = self.family
        gaussians, setup = family.gaussians, family.setup
        codec = getattr(family, "feature_codec", None)
        if codec is not None and not bool(codec.fitted):  # LangSplat: the compression first, on the training frames
            family.feature_source.fit_autoencoder(codec, scene)
        if gaussians.size:
            return
        if getattr(family, "start", None) is not None:
            self.initialise_from_start(scene)
            return
        points, _ = starting_points(scene, setup.init_points, setup.init_depth_stride)
        check = getattr(setup.strategy, "check_start", None)
        if check is not None:  # a strategy with a budget refuses a start above it
            check(points.count)
        rows = rows_from_points(points.xyz, points.rgb, neighbour_scales(points.xyz), sh_degree=gaussians.sh_degree,
                                opacity=setup.init_opacity)
        for name, width in gaussians.channels.items():
            if name == FIELD_CHANNEL:  # lifted from the frames below (no draw: the global RNG as without a field)
                rows[name] = torch.zeros(points.count, width)
                continue
            rows[name] = colour_to_dc(torch.rand(points.count, width))
        gaussians.set_rows({name: value.to(gaussians.means.device) for name, value in rows.items()})
        gaussians.extent.fill_(scene_extent(scene))
        family.start_feature_field(scene)

    def initialise_from_start(self, scene: Scene) -> None:
        """The Gaussians and decoder from ``family.start`` (``generalized_start.begin_from_start``), its notes said
        once on stderr. With a budget (``model.density=budgeted``) a start above ``max_gaussians`` keeps its most
        opaque Gaussians (a point start is refused instead: ``check_start``)."""
        import dataclasses

        from gpnerf_core.model.generalized_start import begin_from_start, most_opaque

        family = self.family
        start = family.start
        budget = getattr(family.setup.strategy, "budget", None)  # BudgetedStrategy's: model.max_gaussians
        if budget is not None:
            kept, note = most_opaque(start.gaussians, int(budget))
            if note is not None:
                start = dataclasses.replace(start, gaussians=kept, notes=(*start.notes, note))
        for note in begin_from_start(family, start, family.start_classes):
            print(f"note: {note}", file=sys.stderr)
        family.start_feature_field(scene)

    def resize_to(self, weights: Mapping[str, Tensor], source: str) -> None:
        self.family.gaussians.take_sizes(weights, "gaussians.", source)
        self.family.empty_source = source if not self.family.gaussians.size else None

    def optimizer_options(self, total_steps: int) -> dict[str, GroupOptions]:
        """3DGS's epsilon for every Gaussian row's group; the centres' rate times the scene's extent, decayed
        log-linearly to ``means_final_ratio`` of it at ``total_steps`` (3DGS's ``get_expon_lr_func`` without delay).
        The family's other groups (a decoder's) keep the run's options."""
        family = self.family
        ratio = family.setup.means_final_ratio

        def means(step: int) -> float:
            t = min(1.0, (step + 1) / max(1, total_steps))
            return float(family.gaussians.extent) * math.exp(math.log(ratio) * t)

        options = {group: GroupOptions(eps=ADAM_EPS) for group in family.row_groups().values()}
        options["means"] = GroupOptions(lr_factor=means, eps=ADAM_EPS)
        return options

    def callbacks(self) -> Sequence[TrainingCallback]:
        return (TrainingCallback(TrainingPhase.BEFORE_STEP, self.colour_degree),
                TrainingCallback(TrainingPhase.BEFORE_BACKWARD, self.keep_gradients),
                TrainingCallback(TrainingPhase.AFTER_BACKWARD, self.density_control),
                TrainingCallback(TrainingPhase.AFTER_STEP, self.check_finite))

    def colour_degree(self, state: TrainingState) -> None:
        """The colour's degree for this step (3DGS raises it at every ``sh_degree_every``-th iteration)."""
        family = self.family
        every = scaled_step(family.setup.sh_degree_every, state.total_steps, family.strategy.schedule_steps)
        family.gaussians.active_degree.fill_(min(family.gaussians.sh_degree, (state.step + 1) // every))

    def keep_gradients(self, state: TrainingState) -> None:
        """The strategy keeps the projected centres' gradients of the step's views."""
        gaussians = self.family.gaussians
        self.family.strategy.step_pre_backward(gaussians, state.optimizer, gaussians.row_state(), state.step,
                                               rasterized(state))

    def density_control(self, state: TrainingState) -> None:
        """The strategy's statistics and density changes, told what the rasterizer reported of the step's views; the
        strategy's note on the run's schedule (``schedule_note``: resets dropped in a short run) printed once."""
        gaussians = self.family.gaussians
        if not getattr(self.family, "schedule_noted", False):
            self.family.schedule_noted = True
            note = getattr(self.family.strategy, "schedule_note", None)
            said = note(state.total_steps) if note is not None else None
            if said:
                from tqdm import tqdm  # the training progress bar's writer: the note on a line of its own

                tqdm.write(f"note: {said}", file=sys.stderr)
        self.family.strategy.scaled(state.total_steps).step_post_backward(
            gaussians, state.optimizer, gaussians.row_state(), state.step, rasterized(state))

    def check_finite(self, state: TrainingState) -> None:
        """NaN or Inf in a Gaussian parameter stops training, naming the family, the parameter and the step."""
        gaussians = self.family.gaussians
        for name, tensor in gaussians.rows().items():
            if all_finite(tensor.detach()):  # one aminmax pass; the mask only to count a bad one
                continue
            finite = torch.isfinite(tensor.detach())
            if not bool(finite.all()):
                bad = int((~finite).reshape(finite.shape[0], -1).any(dim=1).sum()) if tensor.ndim else 1
                raise NonFiniteError(f"step {state.step}: model {self.family.name!r} Gaussian parameter {name!r} holds "
                                     f"NaN or Inf ({bad} of {gaussians.size} Gaussians); training stopped")


class GaussianFamily(ModelFamily):
    """One scene's 3D Gaussians with ``channels`` of the family's own (``{name: width}``, each rasterized beside the
    colour); trained on whole images (``ImageOutput``), densified by ``setup.strategy``.

    Args:
        channels: the family's per-Gaussian channels, by name (a width 0 keeps the name with no channel).
        setup: the checked options (``gaussian_setup`` of the family's ``GaussianSceneConfig``).
        head: the ``+head`` decoding the rendered channels, or None.
        feature_field: the configured feature provider (``ModelParts.feature_field``), or None: with one, each
            Gaussian also carries the channel ``feature_field`` (``FIELD_CHANNEL``: the provider's channels, or
            ``features.channels`` autoencoder codes, ``feature_codec``, fitted on the scene's training frames before
            the Gaussians start), rasterized with the others and decoded to the provider's channels
            (``field_map``, ``field_rows``).
    """

    name: ClassVar[str] = "gaussians"
    """The family's registry name, for messages (each subclass sets its own)."""
    start_channel: ClassVar[str | None] = None
    """The channel a generalizable model's start fills with its features or class scores
    (``gpnerf_core.model.generalized_start``); None: the family takes a start's geometry and colour only."""
    capabilities = Capabilities(generalizable=False, trains_on=TrainingBatch.IMAGES, source_encoding=None,
                                changes_size=True, gaussians=True, hooks=GaussianHooks)

    def __init__(self, *, channels: Mapping[str, int], setup: GaussianSetup,
                 head: PerceptionHead | None = None, feature_field: Any = None) -> None:
        super().__init__()
        self.head = head
        channels = dict(channels)
        self.feature_source = feature_field  # a plain object (the provider is not a submodule: never saved)
        if feature_field is not None:
            channels[FIELD_CHANNEL] = int(feature_field.carried)
        self.feature_codec = feature_field.make_autoencoder() if feature_field is not None else None
        self.gaussians = GaussianParameters(setup.sh_degree, channels)
        self.setup = setup
        self.empty_source: str | None = None  # the checkpoint that gave it 0 Gaussians, named when it renders
        self.schedule_noted = False  # the strategy's schedule note is printed once per run
        self.start: Any = None  # a GaussianStart initialise begins from (use_start), None: the scene's points
        self.start_classes: tuple[str, ...] | None = None  # the scene's class names, checked against the start's
        self.strategy = setup.strategy
        self.strategy.initialize_state(self.gaussians)

    def use_start(self, start: Any, scene_classes: tuple[str, ...] | None = None) -> None:
        """Begin from ``start`` (a ``GaussianStart``) instead of the scene's points when initialised (weights already
        loaded still win); ``scene_classes``: the scene's class names (None: not checked against the start's)."""
        self.start = start
        self.start_classes = tuple(scene_classes) if scene_classes is not None else None

    def begin_decoder(self, start: Any) -> bool:
        """Begin the family's decoder from ``start`` (a ``GaussianStart`` whose features fill ``start_channel``);
        False when the family has no decoder to begin (this base class: none)."""
        return False

    def row_groups(self) -> dict[str, str]:
        """Each Gaussian row -> its learning-rate group: 3DGS's (``BASE_ROWS``), and each channel under its own name."""
        return {**BASE_ROWS, **{name: name for name in self.gaussians.channels}}

    def gaussian_groups(self) -> dict[str, list[nn.Parameter]]:
        """The Gaussians' parameters by learning-rate group (``parameter_groups`` adds the family's decoder)."""
        rows = self.gaussians.rows()
        return {group: [rows[row]] for row, group in self.row_groups().items()}

    def render(self, camera: TargetCamera, stride: int, *, channels: bool
               ) -> tuple[Tensor, Tensor, Tensor, Tensor | None, ViewInfo]:
        """``(rgb [h, w, 3], depth [h, w], alpha [h, w], channel map [h, w, C] or None, info)`` of ``camera`` on a
        ``stride`` grid in one rasterization: the family's channels concatenated in their order (composited without
        a background term, as Gaussian Grouping's identities) when ``channels`` and it has any; ``info``: what the
        rasterizer reported (density control's input)."""
        if not self.gaussians.size:
            if getattr(self, "empty_source", None) is not None:
                raise DataError(f"{self.empty_source}: it holds 0 Gaussians (gaussians.count=0), so model={self.name} "
                                "has nothing to render; expected a checkpoint of a fitted model (one a run wrote "
                                "while training)")
            raise ConfigError(f"model={self.name} has no Gaussians: it is fitted on its scene first (run), or built "
                              "from a checkpoint")
        field = self.gaussians
        colours = sh_colours(field.harmonics(), field.means - camera.c2w[:3, 3].to(field.means.dtype))
        own = [getattr(field, name) for name, width in field.channels.items() if width]
        features = torch.cat([colours, *own], dim=-1) if channels and own else colours
        background = torch.zeros(features.shape[1], dtype=features.dtype, device=features.device)
        background[:3] = self.setup.background
        intrinsics, height, width = strided_camera(camera, stride)
        out = rasterize_gaussians(field.activated(features), intrinsics=intrinsics, c2w=camera.c2w, height=height,
                                  width=width, background=background, backend=self.setup.rasterizer)
        depth = torch.where(out.alpha > 1e-6, out.depth / out.alpha.clamp_min(1e-6), torch.zeros_like(out.depth))
        channel_map = out.features[..., 3:] if features.shape[1] > 3 else None
        info = ViewInfo(means2d=out.means2d, radii=out.radii, height=height, width=width)
        return out.features[..., :3], depth, out.alpha, channel_map, info

    def split_channels(self, channel_map: Tensor) -> dict[str, Tensor]:
        """``render``'s ``[h, w, C]`` channel map cut into each channel's ``[h, w, width]`` (in ``channels`` order)."""
        parts, start = {}, 0
        for name, width in self.gaussians.channels.items():
            parts[name] = channel_map[..., start:start + width]
            start += width
        return parts

    def decode_field(self, codes: Tensor) -> Tensor:
        """``[..., k]`` feature-field codes -> ``[..., C]`` the provider's channels (``feature_codec``'s decoder; the
        codes themselves without compression)."""
        return self.feature_codec.decode(codes) if self.feature_codec is not None else codes

    def field_map(self, channel_map: Tensor) -> Tensor | None:
        """``[1, C, h, w]`` the feature field of ``render``'s channel map, decoded; None without a field."""
        if self.feature_source is None:
            return None
        return self.decode_field(self.split_channels(channel_map)[FIELD_CHANNEL]).permute(2, 0, 1)[None]

    def field_rows(self) -> Tensor | None:
        """``[G, C]`` each Gaussian's feature-field vector in the provider's channels (decoded); None without a
        field (``GaussianScene.feature_field``)."""
        if self.feature_source is None:
            return None
        return self.decode_field(getattr(self.gaussians, FIELD_CHANNEL))

    @torch.no_grad()
    def start_feature_field(self, scene: Scene) -> None:
        """Start each Gaussian's feature-field channel from the provider's features (nothing without a field): the
        feature of the first training frame that sees its centre (in front of the camera, inside the image, and within
        5 % + 1 cm of the frame's depth where it has one), sampled bilinearly at its projection
        (``gpnerf_core.at_pixels``), encoded to codes where compressed; a Gaussian no frame sees takes the mean of the
        others. A start this close leaves the distillation the details to fit, not the whole field from noise."""
        field = self.feature_source
        if field is None or not self.gaussians.size:
            return
        means = self.gaussians.means.detach()
        lifted = means.new_zeros(means.shape[0], field.channels)
        found = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        for index in scene.train_frames:
            frame = scene.load_frame(index)
            height, width = frame.height, frame.width
            pixels, depth = project_points(means, frame.intrinsics[None].to(means), frame.c2w[None].to(means))
            pixels, depth = pixels[0], depth[0]
            seen = (~found & (depth > 1e-3) & (pixels[:, 0] > -0.5) & (pixels[:, 0] < width - 0.5)
                    & (pixels[:, 1] > -0.5) & (pixels[:, 1] < height - 0.5))
            rows = pixels[:, 1].round().clamp(0, height - 1).long()
            cols = pixels[:, 0].round().clamp(0, width - 1).long()
            surface = frame.depth.to(means)[rows, cols]
            seen &= (surface <= 0) | ((depth - surface).abs() <= 0.05 * surface + 0.01)
            if not bool(seen.any()):
                continue
            maps = field.maps(scene.name, [index], frame.rgb.permute(2, 0, 1)[None].to(means))
            lifted[seen] = at_pixels(maps, pixels[seen], (height, width))
            found |= seen
            if bool(found.all()):
                break
        if bool(found.any()) and not bool(found.all()):
            lifted[~found] = lifted[found].mean(dim=0)
        codes = self.feature_codec.encode(lifted) if self.feature_codec is not None else lifted
        getattr(self.gaussians, FIELD_CHANNEL).copy_(codes)

    def render_view(self, camera: TargetCamera, *, channels: bool) -> tuple[ImageOutput, Tensor | None]:
        """A training view rendered whole: ``ImageOutput`` with ``rgb``, ``depth``, ``alpha`` and, in training mode,
        what the rasterizer reported (``extras``: density control reads it), which the family completes with its
        decoded outputs (``dataclasses.replace``); and the ``[H, W, C]`` channel map (or None, as ``render``)."""
        rgb, depth, alpha, channel_map, info = self.render(camera, 1, channels=channels)
        extras = {INFO: info} if self.training else {}
        return ImageOutput(rgb=rgb, depth=depth, alpha=alpha, extras=extras), channel_map
