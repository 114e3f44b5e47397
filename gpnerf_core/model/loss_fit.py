"""Whether a loss set fits the model it trains, and, when it does not, the fix that works for that model: advice
derived from what the family declares (``Capabilities.accepts_head``, a ``model.label_rendering`` switch), what the
dataset holds (a class list, ``dataset.labels_from``) and what the loss set declares (``LossSet.head_predicts``, the
weights whose terms need semantics), never from family names."""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.interfaces import LossSet
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.interfaces.model import ModelFamily, TrainingBatch
from gpnerf_core.registry.components import Registry


def declared_head_predicts(cfg: Any, registry: Registry) -> Predicts | None:
    """What the loss set ``cfg.loss`` names declares its scores must be, before it is built: a ``head_predicts`` its
    factory (a ``LossSet`` subclass) fixes for every configuration; None when it depends on the options."""
    factory = registry.get("loss", str(cfg.loss.name)).spec.factory
    declared = getattr(factory, "head_predicts", None) if isinstance(factory, type) else None
    return Predicts(declared) if declared is not None else None


def check_predictions_fit(cfg: Any, model: ModelFamily, wanted: Predicts | None) -> None:
    """The model's semantic scores are what the loss set trains (``wanted``: ``LossSet.head_predicts``).

    Raises:
        ConfigError: they are not, naming the fix that works for this family (another head where it takes one).
    """
    output = model.semantic_output
    if wanted is None or output is None or output.predicts is wanted:
        return
    predicts = output.predicts.value
    rays = model.capabilities.trains_on is TrainingBatch.RAYS
    other_loss = f"+loss={'instance' if output.predicts is Predicts.INSTANCES else 'dgs' if rays else 'image'}"
    if cfg.get("head") is not None or model.capabilities.accepts_head:
        owner = f"head {cfg.head.name!r}" if cfg.get("head") is not None else f"model {cfg.model.name!r}"
        what = "an instance head (+head=instance)" if wanted is Predicts.INSTANCES else "a class head"
        raise ConfigError(f"loss {cfg.loss.name!r} trains {wanted.value} but {owner} predicts {predicts}; use {what} "
                          f"or a loss set for {predicts} ({other_loss})")
    raise ConfigError(f"loss {cfg.loss.name!r} trains {wanted.value} but model {cfg.model.name!r} predicts {predicts} "
                      f"and takes no head (Capabilities.accepts_head is False); use a loss set for {predicts} (an "
                      f"experiment's own, or loss={other_loss.split('=')[1].replace('dgs', 'ce')}), or a family that "
                      f"takes a head for {wanted.value}")


def check_loss_fits(cfg: Any, model: ModelFamily, loss: LossSet, *, num_classes: int | None = None,
                    registry: Registry | None = None) -> None:
    """The loss set reads only what the model renders: semantic outputs, and scores of the kind it trains.

    Args:
        num_classes: the classes the model was built with (0: the dataset has no class list); None: unknown.
        registry: where the loss set was built from (used to find the weights that turn its semantic terms off).
    """
    if getattr(loss, "needs_whole_images", False) and model.capabilities.trains_on is not TrainingBatch.IMAGES:
        raise ConfigError(f"loss {cfg.loss.name!r} reads whole images, and model {cfg.model.name!r} trains on random "
                          f"rays; use a loss set on rays (+loss=ce, +loss=dgs, ...) or a model that renders whole "
                          f"images (model=mvsplat)")
    wanted = Predicts(loss.head_predicts) if loss.head_predicts is not None else None
    if loss.needs_semantics and model.semantic_output is None:
        raise ConfigError(no_semantics_message(cfg, model, wanted, num_classes, semantic_weights(cfg, registry)))
    check_predictions_fit(cfg, model, wanted)


def no_semantics_message(cfg: Any, model: ModelFamily, wanted: Predicts | None, num_classes: int | None,
                         weights: tuple[str, ...]) -> str:
    """Why a model renders no semantics for a loss set that needs them, and the fixes that work for it: without a
    class list, labels from elsewhere or colour only; otherwise the family's own switch, a head where it takes one,
    or colour only."""
    colour_only = " ".join(f"loss.{key}=0" for key in weights)
    fixes: list[str] = []
    if num_classes == 0 and cfg.get("head") is None and wanted is not Predicts.INSTANCES:
        reason = (f"dataset {cfg.dataset.name!r} has no labels (no class list), so model {cfg.model.name!r} renders "
                  f"no semantics")
        if colour_only:
            fixes.append(f"train colour only ({colour_only})")
        if "labels_from" in cfg.dataset:
            fixes.append("train on a trained model's labels of it (`label checkpoint=<.pt>`, then "
                         "dataset.labels_from=<its out_dir>)")
        if not fixes:
            fixes.append("use a dataset with labels or a loss set without semantic terms")
        return f"loss {cfg.loss.name!r} needs semantics but {reason}; {', or '.join(fixes)}"
    switch = cfg.model.get("label_rendering")
    if switch is not None and not bool(switch) and wanted is not Predicts.INSTANCES:
        fixes.append("render class scores (model.label_rendering=true)")
    if model.capabilities.accepts_head:
        fixes.append(f"decode with a head ({'+head=instance' if wanted is Predicts.INSTANCES else '+head=unet'}) and "
                     f"keep the model's semantic outputs on")
    if colour_only:
        fixes.append(f"train colour only ({colour_only})")
    if not fixes:
        fixes.append("use a loss set without semantic terms")
    configured = " (model.label_rendering=false)" if switch is not None and not bool(switch) else ""
    return (f"loss {cfg.loss.name!r} needs semantics but model {cfg.model.name!r} renders none as "
            f"configured{configured}; {', or '.join(fixes)}")


def semantic_weights(cfg: Any, registry: Registry | None) -> tuple[str, ...]:
    """The ``loss.<term>_weight`` keys whose terms need semantics: each non-zero weight that, kept alone, builds a
    loss set with ``needs_semantics``; () when zeroing them all leaves a loss set that still needs semantics or
    cannot be built (no colour-only variant of this loss set)."""
    if registry is None:
        return ()
    node = OmegaConf.to_container(cfg.loss, resolve=True) if OmegaConf.is_config(cfg.loss) else dict(cfg.loss)
    weights = [key for key, value in node.items() if key.endswith("_weight") and isinstance(value, (int, float))
               and not isinstance(value, bool) and value > 0]

    def needs_semantics(zeroed: list[str]) -> bool | None:
        try:
            return bool(registry.build("loss", {**node, **{key: 0.0 for key in zeroed}}).needs_semantics)
        except GpnerfError:
            return None

    semantic = tuple(key for key in weights if needs_semantics([other for other in weights if other != key]))
    return semantic if semantic and needs_semantics(list(semantic)) is False else ()
