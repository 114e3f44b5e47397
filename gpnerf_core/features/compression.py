"""A per-scene autoencoder that compresses a feature provider's channels to the few a Gaussian carries (LangSplat).

LangSplat (Qin et al., CVPR 2024) fits, per scene, an MLP autoencoder on the CLIP features of the scene's training
images (512 -> 3 channels) before its Gaussians are trained, and renders the low-dimensional codes; a rendered code is
decoded back to CLIP's space to be queried. ``FeatureAutoencoder`` is that, for any provider: ``C`` channels to ``k``
(at most 16, ``features.channels``), one hidden layer each way, fitted by ``fit`` on the training frames' features
(mean squared error plus 1 - cosine, Adam), then frozen: the family renders codes, decodes them, and its distillation
term and every query read the decoded features. Its reconstruction error on the samples it was fitted on (mean cosine
similarity and mean L2 distance) is kept in its buffers, so a checkpoint carries it and evaluation reports it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError

MAX_CODE_CHANNELS = 16
"""The most channels a compressed feature field keeps per Gaussian (Gaussian Grouping's identity width)."""


@dataclass(frozen=True)
class ReconstructionError:
    """How well an autoencoder gives back the features it was fitted on.

    Attributes:
        cosine: mean cosine similarity between each feature vector and its reconstruction (1 = same directions).
        l2: mean Euclidean distance between each vector and its reconstruction, in the provider's units.
        relative_l2: the same distance over the vector's norm, averaged.
        samples: how many vectors were compared.
    """

    cosine: float
    l2: float
    relative_l2: float
    samples: int

    def as_metrics(self) -> dict[str, float | int]:
        """``{features/autoencoder_cosine, ..._l2, ..._relative_l2, ..._samples}`` for metrics.json and the log."""
        return {"features/autoencoder_cosine": self.cosine, "features/autoencoder_l2": self.l2,
                "features/autoencoder_relative_l2": self.relative_l2, "features/autoencoder_samples": self.samples}


def reconstruction_error(features: Tensor, reconstructed: Tensor) -> ReconstructionError:
    """``features`` and ``reconstructed`` ``[N, C]`` compared vector by vector (``ReconstructionError``)."""
    features, reconstructed = features.float(), reconstructed.float()
    cosine = F.cosine_similarity(features, reconstructed, dim=-1, eps=1e-8)
    distance = (features - reconstructed).norm(dim=-1)
    relative = distance / features.norm(dim=-1).clamp_min(1e-8)
    return ReconstructionError(cosine=float(cosine.mean()), l2=float(distance.mean()),
                               relative_l2=float(relative.mean()), samples=int(features.shape[0]))


class FeatureAutoencoder(nn.Module):
    """``C`` -> ``k`` -> ``C`` channels: an MLP encoder and decoder with one hidden layer of ``hidden`` units each
    (ReLU). Its parameters never train with the model (``requires_grad`` False outside ``fit``), so a family's
    optimizer leaves them out; ``fitted`` and the reconstruction error are buffers (saved in checkpoints).

    Args:
        channels: C, the provider's channels; code: k in [1, 16] (< C); hidden: the hidden width.
    """

    def __init__(self, channels: int, code: int, hidden: int = 64) -> None:
        super().__init__()
        if not 1 <= int(code) <= MAX_CODE_CHANNELS or int(code) >= int(channels):
            raise ConfigError(f"features.channels={code}: expected an integer in [1, {MAX_CODE_CHANNELS}] below the "
                              f"provider's {channels} channels")
        if int(hidden) < 1:
            raise ConfigError(f"features.autoencoder_hidden={hidden}: expected an integer >= 1")
        self.channels, self.code = int(channels), int(code)
        self.encoder = nn.Sequential(nn.Linear(self.channels, hidden), nn.ReLU(), nn.Linear(hidden, self.code))
        self.decoder = nn.Sequential(nn.Linear(self.code, hidden), nn.ReLU(), nn.Linear(hidden, self.channels))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        self.register_buffer("error", torch.zeros(3))  # cosine, l2, relative_l2 on the fitting samples
        self.register_buffer("error_samples", torch.zeros((), dtype=torch.long))
        self.requires_grad_(False)

    def encode(self, features: Tensor) -> Tensor:
        """``[..., C]`` -> ``[..., k]``."""
        return self.encoder(features)

    def decode(self, codes: Tensor) -> Tensor:
        """``[..., k]`` -> ``[..., C]``."""
        return self.decoder(codes)

    def decode_map(self, codes: Tensor) -> Tensor:
        """``[N, k, h, w]`` -> ``[N, C, h, w]``."""
        return self.decoder(codes.movedim(1, -1)).movedim(-1, 1)

    def fit(self, features: Tensor, *, steps: int, lr: float, seed: int = 0, batch: int = 4096) -> ReconstructionError:
        """Fit on ``features`` ``[N, C]`` (the training frames' provider cells): ``steps`` Adam steps at ``lr`` on
        mini-batches of ``batch`` vectors (drawn with a generator seeded by ``seed``: the global RNG is untouched) of
        mean squared error + (1 - cosine similarity); then frozen, marked fitted, and its error on all ``features``
        kept and returned."""
        if features.ndim != 2 or int(features.shape[1]) != self.channels or not features.shape[0]:
            raise ConfigError(f"the feature autoencoder fits [N, {self.channels}] features; got "
                              f"{list(features.shape)}")
        if int(steps) < 1:
            raise ConfigError(f"features.autoencoder_steps={steps}: expected an integer >= 1")
        features = features.detach().float()
        generator = torch.Generator(device="cpu").manual_seed(int(seed))
        self.requires_grad_(True)
        optimizer = torch.optim.Adam(self.parameters(), lr=float(lr))
        try:
            with torch.enable_grad():
                for _ in range(int(steps)):
                    pick = torch.randint(int(features.shape[0]), (min(int(batch), int(features.shape[0])),),
                                         generator=generator).to(features.device)
                    x = features[pick]
                    y = self.decode(self.encode(x))
                    loss = F.mse_loss(y, x) + (1 - F.cosine_similarity(y, x, dim=-1, eps=1e-8)).mean()
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    optimizer.step()
        finally:
            self.requires_grad_(False)
            for parameter in self.parameters():
                parameter.grad = None
        with torch.no_grad():
            error = reconstruction_error(features, self.decode(self.encode(features)))
        self.fitted.fill_(True)
        self.error.copy_(torch.tensor([error.cosine, error.l2, error.relative_l2]))
        self.error_samples.fill_(error.samples)
        return error

    def reconstruction(self) -> ReconstructionError | None:
        """The error ``fit`` measured (kept in the buffers), or None before a fit."""
        if not bool(self.fitted):
            return None
        cosine, l2, relative = (float(v) for v in self.error)
        return ReconstructionError(cosine=cosine, l2=l2, relative_l2=relative, samples=int(self.error_samples))
