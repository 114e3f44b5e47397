"""Building the ``semantic_3dgs`` family from its options and the configured head."""

from __future__ import annotations

from typing import Any

from gpnerf_core import ConfigError, ModelParts, gaussian_setup
from gpnerf_plugins.families.semantic_3dgs.model import Semantic3DGS


def build_semantic_3dgs(*, parts: ModelParts, feature_dim: int = 16, **options: Any) -> Semantic3DGS:
    """The family for the dataset's classes: a 1 x 1 convolution decodes the rendered features without a ``+head``,
    the head with one (it decodes ``feature_dim`` channels in one level); ``options``: 3DGS's
    (``GaussianSceneConfig``), checked by ``gaussian_setup``."""
    if isinstance(feature_dim, bool) or not isinstance(feature_dim, int) or feature_dim < 1:
        raise ConfigError(f"model.feature_dim={feature_dim!r}: expected an integer >= 1")
    setup = gaussian_setup(options)
    head = parts.head(in_dim=feature_dim, in_levels=1) if parts.configured("head") else None
    return Semantic3DGS(head=head, num_classes=parts.num_classes, feature_dim=feature_dim, setup=setup)
