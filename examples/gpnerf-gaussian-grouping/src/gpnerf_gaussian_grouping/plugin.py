"""The plugin module the ``gpnerf`` entry point names: the family's factory and the hook implementations."""

from __future__ import annotations

from typing import Any

from gpnerf_core import ComponentSpec, ConfigError, ModelParts, gaussian_setup, hookimpl
from gpnerf_gaussian_grouping.config import GaussianGroupingConfig
from gpnerf_gaussian_grouping.model import GaussianGrouping

C = GaussianGroupingConfig


def build_gaussian_grouping(*, parts: ModelParts, identity_dim: int = C.identity_dim, slots: int = C.slots,
                            reg3d_every: int = C.reg3d_every, reg3d_k: int = C.reg3d_k,
                            reg3d_sample_size: int = C.reg3d_sample_size, reg3d_max_points: int = C.reg3d_max_points,
                            **options: Any) -> GaussianGrouping:
    """The family from its options; 3DGS's (``options``) checked by ``gaussian_setup``. A ``+head`` is refused: its
    own classifier decodes the identities."""
    if parts.configured("head"):
        raise ConfigError(f"model=gaussian_grouping classifies its identities with its own 1 x 1 classifier; drop "
                          f"+head={parts.name('head')}")
    own = {"identity_dim": identity_dim, "slots": slots, "reg3d_every": reg3d_every, "reg3d_k": reg3d_k,
           "reg3d_sample_size": reg3d_sample_size, "reg3d_max_points": reg3d_max_points}
    for key, value in own.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"model.{key}={value!r}: expected an integer >= 1")
    reg3d = {key.removeprefix("reg3d_"): value for key, value in own.items() if key.startswith("reg3d_")}
    return GaussianGrouping(identity_dim=identity_dim, slots=slots, reg3d=reg3d, setup=gaussian_setup(options))


@hookimpl
def gpnerf_register_models() -> list[ComponentSpec]:
    return [ComponentSpec("gaussian_grouping", build_gaussian_grouping, GaussianGroupingConfig,
                          "per-scene 3D Gaussians with identity encodings, classified into instances (ECCV 2024)",
                          display_name="Gaussian Grouping")]


@hookimpl
def gpnerf_config_searchpaths() -> list[str]:
    return ["pkg://gpnerf_gaussian_grouping.conf"]
