"""A trained checkpoint's own image encoder, with its trained weights: what the ``teacher`` feature provider runs."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.feature_extractor import FeatureExtractor
from gpnerf_core.model.build import build_model
from gpnerf_core.model.trained import load_trained
from gpnerf_core.model.weights import load_weights


def trained_feature_extractor(path: str | Path, key: str = "checkpoint") -> tuple[FeatureExtractor, str, str]:
    """The feature extractor of the model a checkpoint holds, its trained weights loaded, frozen in eval mode.

    The model is built from the checkpoint's own config and classes, its weights (the average where the run kept one)
    loaded, and the first module that implements ``FeatureExtractor`` is returned.

    Args:
        path: the checkpoint file (a run's ``checkpoints/*.pt``).
        key: the option that named it, for the errors (``feature_provider.checkpoint``).

    Returns:
        ``(extractor, the model family's name, the checkpoint's config hash and step)``.

    Raises:
        DataError: the file is missing, unreadable or damaged; ConfigError: its model has no feature extractor.
    """
    trained = load_trained(path, key)
    cfg = OmegaConf.create(trained.config_yaml)
    classes = trained.classes
    model = build_model(cfg, classes.num_classes if classes is not None else 0)
    weights, which = trained.weights("average")
    load_weights(model, weights, f"{key}={path}")
    extractor = next((m for m in model.modules() if isinstance(m, FeatureExtractor)), None)
    if extractor is None:
        raise ConfigError(f"{key}={path}: model {trained.family!r} has no feature extractor (no FeatureExtractor "
                          "module) whose maps the teacher provider could give")
    extractor.eval().requires_grad_(False)
    return extractor, trained.family, f"{trained.config_sha256}|step {trained.step}|{which}"
