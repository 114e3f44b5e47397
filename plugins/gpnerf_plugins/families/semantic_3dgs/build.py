"""Building the ``semantic_3dgs`` family from its options and the configured head."""

from __future__ import annotations

from typing import Any

from gpnerf_core import ConfigError, ModelParts, gaussian_setup
from gpnerf_plugins.families.semantic_3dgs.model import Semantic3DGS


def build_semantic_3dgs(*, parts: ModelParts, feature_dim: int = 16, feature_levels: int = 1, feature_stride: int = 1,
                        **options: Any) -> Semantic3DGS:
    """The family for the dataset's classes: a 1 x 1 convolution decodes the rendered features without a ``+head``,
    the head with one (it decodes ``feature_dim`` channels in ``feature_levels`` levels, rendered every
    ``feature_stride`` pixels); with ``+feature_provider`` a feature field per Gaussian as well
    (``parts.feature_field()``); ``options``: 3DGS's (``GaussianSceneConfig``), checked by ``gaussian_setup``."""
    for key, value in (("feature_dim", feature_dim), ("feature_levels", feature_levels),
                       ("feature_stride", feature_stride)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"model.{key}={value!r}: expected an integer >= 1")
    if feature_dim % feature_levels:
        raise ConfigError(f"model.feature_levels={feature_levels}: expected a divisor of model.feature_dim="
                          f"{feature_dim} (equal channel blocks of each Gaussian's feature)")
    setup = gaussian_setup(options)
    head = parts.head(in_dim=feature_dim, in_levels=feature_levels) if parts.configured("head") else None
    return Semantic3DGS(head=head, num_classes=parts.num_classes, feature_dim=feature_dim, setup=setup,
                        feature_stride=feature_stride, feature_field=parts.feature_field())
