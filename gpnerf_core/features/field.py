"""What a model family is handed to carry a feature field (``ModelParts.feature_field``), and the distillation term.

With ``+feature_provider=<name>`` a family that renders a feature field (``Capabilities.feature_field``) builds it
through ``parts.feature_field()``: a ``FeatureField`` naming the provider's channels ``C`` and grid (``stride`` image
pixels per cell), the channels the family should carry (``carried``: ``C``, or ``features.channels`` <= 16 when the
provider has more, with a per-scene ``FeatureAutoencoder`` the family owns), and the provider's maps of any frame
(``maps``: through the on-disk cache for a dataset's frames). The trainer adds the distillation term
(``distillation_term``, ``train/feature_field``) on what the family rendered (``ImageOutput.features``,
``RenderedRays.features``) against the provider's map of the target frame:

* a whole image (``[1, C, H, W]``, any grid finer than the provider's) is averaged over each provider cell
  (``to_grid``: area pooling) and compared cell by cell;
* rays (``[R, C]``) are compared with the provider's map sampled bilinearly at the rays' pixels (``at_pixels``).
"""

from __future__ import annotations

import contextlib
import math
import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.features.compression import MAX_CODE_CHANNELS, FeatureAutoencoder, ReconstructionError

FEATURE_LOSSES = ("cosine", "l1")
"""``features.loss``: 1 - cosine similarity per cell or ray, or the mean absolute difference per channel."""
TERM = "feature_field"
"""The distillation term's name (logged as ``train/feature_field``)."""

Reader = Callable[[Any, Any, str, Sequence[int]], Tensor]
"""``(provider, dataset, scene, frames) -> [n, C, h, w]``: a provider's maps of a dataset's frames (the cache's)."""


@dataclass(frozen=True)
class FeatureFieldOptions:
    """The ``features`` config section, checked (``from_config``; the fields as ``FeaturesConfig`` documents them)."""

    loss: str = "cosine"
    weight: float = 1.0
    channels: int = 16
    autoencoder_steps: int = 1000
    autoencoder_hidden: int = 128
    autoencoder_lr: float = 2e-3
    autoencoder_samples: int = 65536

    @classmethod
    def from_config(cls, section: Any) -> "FeatureFieldOptions":
        """The options of a ``features`` section (None: the defaults); a ConfigError naming the key and what is
        expected for a value out of range."""
        values = {key: section.get(key) for key in cls.__dataclass_fields__} if section is not None else {}
        options = cls(**{key: value for key, value in values.items() if value is not None})
        if options.loss not in FEATURE_LOSSES:
            raise ConfigError(f"features.loss={options.loss!r}: expected one of {', '.join(FEATURE_LOSSES)}")
        weight = options.weight
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) or weight < 0:
            raise ConfigError(f"features.weight={weight!r}: expected a finite number >= 0")
        for key, low, high in (("channels", 0, MAX_CODE_CHANNELS), ("autoencoder_steps", 1, None),
                               ("autoencoder_hidden", 1, None), ("autoencoder_samples", 1, None)):
            value = getattr(options, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and
                                                                                         value > high):
                bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
                raise ConfigError(f"features.{key}={value!r}: expected an integer {bound}")
        rate = options.autoencoder_lr
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
            raise ConfigError(f"features.autoencoder_lr={rate!r}: expected a finite number > 0")
        return options


class FeatureField:
    """A feature provider as a family's feature field sees it.

    Args:
        provider: the built provider (``channels``, ``stride``, ``compute``, ``fingerprint``).
        options: the ``features`` section (``FeatureFieldOptions``).
        name: the provider's configured name (for messages).
        dataset: the run's dataset, whose frames ``maps`` reads through ``reader``; None: computed from the images.
        reader: the cache's accessor (``frame_features``); None: ``provider.compute`` on the images.
    """

    def __init__(self, provider: Any, options: FeatureFieldOptions, *, name: str, dataset: Any = None,
                 reader: Reader | None = None) -> None:
        self.provider, self.options, self.name = provider, options, str(name)
        self.dataset, self.reader = dataset, reader
        self.channels = int(provider.channels)
        self.stride = int(provider.stride)
        self.autoencoder: FeatureAutoencoder | None = None
        """The family's autoencoder once it made one (``make_autoencoder``): evaluation reports its error."""

    @property
    def compressed(self) -> bool:
        """The provider has more channels than ``features.channels`` (> 0) lets a Gaussian carry."""
        return 0 < self.options.channels < self.channels

    @property
    def carried(self) -> int:
        """Channels a family that compresses carries per primitive: ``features.channels`` or the provider's."""
        return self.options.channels if self.compressed else self.channels

    def make_autoencoder(self) -> FeatureAutoencoder | None:
        """A new ``FeatureAutoencoder`` ``C`` -> ``carried`` (None when not ``compressed``), kept as ``autoencoder``;
        the family owns it (a submodule: saved in its checkpoints) and fits it (``fit_autoencoder``). Its weights
        start aside from the global RNG (``quiet_rng``), which the model's own start draws from."""
        if not self.compressed:
            return None
        with quiet_rng():
            self.autoencoder = FeatureAutoencoder(self.channels, self.carried, self.options.autoencoder_hidden)
        return self.autoencoder

    def maps(self, scene: str | None, frames: Sequence[int] | None, images: Tensor) -> Tensor:
        """``[n, C, h, w]`` float32 the provider's maps of ``images`` ``[n, 3, H, W]`` in [0, 1], on their device: the
        dataset's frames ``frames`` of ``scene`` through the cache where both are known and a reader is set, else
        computed from the images. A map of another channel count than ``channels`` is a DataError naming the
        provider."""
        if scene is not None and frames is not None and self.reader is not None and self.dataset is not None:
            maps = self.reader(self.provider, self.dataset, str(scene), [int(f) for f in frames])
        else:
            with torch.no_grad():
                maps = self.provider.compute(scene, list(frames) if frames is not None else [], images)
        maps = maps.to(images.device, torch.float32)
        if maps.ndim != 4 or int(maps.shape[1]) != self.channels or int(maps.shape[0]) != int(images.shape[0]):
            raise DataError(f"feature provider {self.name!r} gave maps {list(maps.shape)} for {int(images.shape[0])} "
                            f"image(s); expected [{int(images.shape[0])}, {self.channels}, h, w]")
        return maps

    def training_samples(self, scene: Any, device: torch.device | str = "cpu") -> Tensor:
        """``[N, C]`` the provider's cells of ``scene``'s training frames (a ``Scene``; its frames loaded one by one),
        on ``device``, at most ``features.autoencoder_samples`` drawn without replacement by a generator seeded 0 (the
        global RNG is untouched): what the autoencoder fits."""
        cells = []
        for index in scene.train_frames:
            image = scene.load_frame(index).rgb.permute(2, 0, 1)[None].to(device)
            cells.append(self.maps(scene.name, [index], image)[0].flatten(1).T)
        samples = torch.cat(cells)
        limit = int(self.options.autoencoder_samples)
        if samples.shape[0] > limit:
            pick = torch.randperm(int(samples.shape[0]), generator=torch.Generator().manual_seed(0))[:limit]
            samples = samples[pick.to(samples.device)]
        return samples

    def fit_autoencoder(self, autoencoder: FeatureAutoencoder, scene: Any) -> ReconstructionError:
        """Fit ``autoencoder`` on ``scene``'s training frames (``training_samples``) with ``features.autoencoder_*``;
        its error said on stderr in one line."""
        device = next(autoencoder.parameters()).device
        error = autoencoder.fit(self.training_samples(scene, device), steps=self.options.autoencoder_steps,
                                lr=self.options.autoencoder_lr)
        print(f"note: feature field: {self.name}'s {self.channels} channels compressed to {self.carried} by an "
              f"autoencoder fitted on {error.samples} cells of scene {scene.name!r}: reconstruction mean cosine "
              f"{error.cosine:.4f}, mean L2 {error.l2:.4f} (relative {error.relative_l2:.4f})", file=sys.stderr)
        return error


@contextlib.contextmanager
def quiet_rng(seed: int | None = None) -> Iterator[None]:
    """Within the block the global CPU RNG is seeded ``seed`` (None: the run's seed, ``torch.initial_seed()``, plus
    57); its state is restored after: what a feature field builds or draws (a provider's layers, an autoencoder, a
    projection, the Gaussians' field channel) takes nothing the model's other parameters and density control would
    have drawn, so a run with ``+feature_provider`` starts and densifies every other parameter as one without."""
    chosen = (torch.initial_seed() + 57) % (2 ** 63) if seed is None else int(seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(chosen)
        yield


def to_grid(rendered: Tensor, size: tuple[int, int]) -> Tensor:
    """``[N, C, H, W]`` rendered features on the provider's ``size`` ``(h, w)`` grid: the mean over each cell's
    pixels where the grid divides the render (area pooling), else bilinear resampling (a render coarser than the
    provider's grid, or one it does not divide)."""
    height, width = int(rendered.shape[-2]), int(rendered.shape[-1])
    if (height, width) == tuple(size):
        return rendered
    if height % size[0] == 0 and width % size[1] == 0:
        return F.avg_pool2d(rendered, kernel_size=(height // size[0], width // size[1]))
    return F.interpolate(rendered, size=size, mode="bilinear", align_corners=False)


def at_pixels(maps: Tensor, pixels: Tensor, image_size: tuple[int, int]) -> Tensor:
    """``[R, C]`` the ``[1, C, h, w]`` map sampled bilinearly at ``pixels`` ``[R, 2]`` ``(u, v)`` of an image of
    ``image_size`` ``(H, W)`` (integer values at pixel centres): the map's cells cover the image evenly, so pixel
    ``(u, v)`` sits at ``((u + 0.5) / W, (v + 0.5) / H)`` of it (``grid_sample`` with ``align_corners=False``, edge
    values held at the border)."""
    height, width = image_size
    grid = torch.stack([(2 * pixels[:, 0].float() + 1) / width - 1, (2 * pixels[:, 1].float() + 1) / height - 1],
                       dim=-1).to(maps.dtype)
    sampled = F.grid_sample(maps, grid[None, :, None, :], mode="bilinear", padding_mode="border",
                            align_corners=False)
    return sampled[0, :, :, 0].T


def lift_to_pixels(maps: Tensor, size: tuple[int, int]) -> Tensor:
    """``[V, C, H, W]`` the ``[V, C, h, w]`` maps at every pixel of ``size`` ``(H, W)`` images (bilinear, the cells
    covering each image evenly: ``at_pixels`` at every pixel centre)."""
    return F.interpolate(maps, size=size, mode="bilinear", align_corners=False)


def feature_distance(rendered: Tensor, target: Tensor, loss: str) -> Tensor:
    """The mean distance of ``rendered`` and ``target`` ``[N, C]`` (``features.loss``): 1 - cosine similarity per
    vector, or the absolute difference per channel."""
    if loss == "cosine":
        return (1 - F.cosine_similarity(rendered.float(), target.float(), dim=-1, eps=1e-8)).mean()
    if loss == "l1":
        return (rendered.float() - target.float()).abs().mean()
    raise ConfigError(f"features.loss={loss!r}: expected one of {', '.join(FEATURE_LOSSES)}")


def view_term(field: FeatureField, view: Any, output: Any) -> Tensor | None:
    """The distillation distance of one target view (``TargetView``) and what the family rendered of it: an
    ``ImageOutput``'s ``features`` ``[1, C, H, W]`` on the provider's grid, or the rays' ``features`` ``[R, C]`` (the
    last pass's) against the map at the rays' pixels. None when the family rendered no field for it."""
    rendered = getattr(output, "features", None)
    rays = None
    if rendered is None and hasattr(output, "last"):
        rays = output.last
        rendered = rays.features
    if rendered is None:
        return None
    target = field.maps(view.scene, [view.frame], view.image[None])
    if rays is None:
        pooled = to_grid(rendered, (int(target.shape[-2]), int(target.shape[-1])))
        return feature_distance(pooled[0].flatten(1).T, target[0].flatten(1).T, field.options.loss)
    return feature_distance(rendered, at_pixels(target, view.pixels, view.camera.image_size), field.options.loss)


def distillation_term(field: FeatureField, batch: Any, output: Any) -> Tensor | None:
    """The unweighted distillation term of a step: ``view_term`` averaged over the views that rendered a field
    (None when none did)."""
    terms = [term for view, out in zip(batch.views, output.views)
             if (term := view_term(field, view, out)) is not None]
    if not terms:
        return None
    return sum(terms) / len(terms)


def image_cosine(rendered: Tensor, target: Tensor) -> float:
    """Mean cosine similarity of a rendered field ``[C, h', w']`` brought to the provider's grid (``to_grid``) and
    the provider's map ``[C, h, w]`` of the real frame, cell by cell (the feature-fidelity protocol's per-image
    value)."""
    pooled = to_grid(rendered[None].float(), (int(target.shape[-2]), int(target.shape[-1])))[0]
    return float(F.cosine_similarity(pooled.flatten(1).T, target.float().flatten(1).T, dim=-1, eps=1e-8).mean())
