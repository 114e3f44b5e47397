"""Building the ``dm_nerf`` family from its options: it builds no parts (no extractor, no head)."""

from __future__ import annotations

from gpnerf_core import ConfigError, ModelParts
from gpnerf_plugins.families.dm_nerf.config import DMNeRFConfig
from gpnerf_plugins.families.dm_nerf.model import DMNeRF

C = DMNeRFConfig


def build_dm_nerf(*, parts: ModelParts, slots: int = C.slots, coarse_samples: int = C.coarse_samples,
                  fine_samples: int = C.fine_samples, width: int = C.width, depth: int = C.depth, skip: int = C.skip,
                  position_scale: float = C.position_scale, position_frequencies: int = C.position_frequencies,
                  direction_frequencies: int = C.direction_frequencies, density_noise: float = C.density_noise,
                  inverse_depth: bool = C.inverse_depth) -> DMNeRF:
    """DM-NeRF with ``slots`` object slots; a configured ``+head`` is refused (its object field renders the slots)."""
    if parts.configured("head"):
        raise ConfigError(f"model=dm_nerf renders object slots per sample with its own object field and decodes no "
                          f"feature map: drop +head={parts.name('head')}")
    return DMNeRF(slots=slots, coarse_samples=coarse_samples, fine_samples=fine_samples, width=width, depth=depth,
                  skip=skip, position_scale=position_scale, position_frequencies=position_frequencies,
                  direction_frequencies=direction_frequencies, density_noise=density_noise,
                  inverse_depth=inverse_depth)
