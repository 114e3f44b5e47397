"""Interface of a stress case: a graded condition a trained model is evaluated under (``gpnerf_core stress``)."""

from __future__ import annotations

from abc import ABC
from typing import Any, Callable, Sequence

import torch

from gpnerf_core.types import Scene, SourceViews

ChooseSources = Callable[[Scene, int, int], list[int]]
"""``(scene, target index, number of views) -> source frame indices``: the model's own view selector."""


class StressCase(ABC):
    """One kind of stress, evaluated at graded levels against the clean condition.

    A case changes what a trained model is given for each held-out target view, never the model: which source
    frames and how many (``source_indices``), what they look like or where their cameras are said to be
    (``perturb_sources``), which held-out target views are scored (``target_frames``), or which data is evaluated
    (``dataset_overrides``, ``split``). A per-scene model has no source views and renders only its own scene: the
    cases that apply to it change only ``target_frames`` (the others are skipped with the reason). The suite evaluates
    the clean condition once per model and every level of every chosen case; a level a dataset cannot offer is
    skipped with the reason ``unavailable`` gives.

    Class attributes:
        name: the case's name on the command line (``--cases``), snake_case.
        description: one line for ``stress --list``.
        axis: what a level's value measures, with its unit (the x axis of the case's plot).
        levels: the level values from mildest to most severe.
        quick_levels: the levels ``--quick`` evaluates (default: the most severe one).
        labels: optional text per level for tables (default: the value).
        split: ``train`` (held-out frames of the training scenes) or ``unseen`` (scenes never trained on).
    """

    name: str = ""
    description: str = ""
    axis: str = "severity"
    levels: tuple[float, ...] = ()
    quick_levels: tuple[float, ...] = ()
    labels: dict[float, str] = {}
    split: str = "train"

    def label(self, level: float) -> str:
        return self.labels.get(level, f"{level:g}")

    def chosen_levels(self, quick: bool) -> tuple[float, ...]:
        return (self.quick_levels or self.levels[-1:]) if quick else self.levels

    def dataset_overrides(self, level: float, dataset_config: Any) -> dict[str, Any]:
        """Dataset config keys to change for this level (``{}``: the model's own data). A key the run's dataset
        config does not have skips the level, naming the key (the variant cannot be made from that dataset).

        Args:
            dataset_config: the run's ``dataset`` section (read-only).
        """
        return {}

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        """Why this level cannot be evaluated on these scenes (None: it can). The suite prints it and skips."""
        return None

    def target_frames(self, level: float, scene: Scene, eval_frames: Sequence[int]) -> list[int]:
        """The held-out frames of ``scene`` scored at this level (default: all of ``eval_frames``, the scene's
        held-out frames in order). A subset only: a frame outside ``eval_frames`` is refused (a training frame would be
        scored against the data the model was fitted on). The suite's per-scene view cap applies afterwards."""
        return list(eval_frames)

    def num_source_views(self, level: float, trained: int) -> int:
        """Source views per target at this level (``trained``: the model's ``model.num_source_views``)."""
        return trained

    def source_indices(
        self, level: float, scene: Scene, target: int, num_views: int, choose: ChooseSources
    ) -> list[int]:
        """Source frames for target frame ``target`` (never the target itself; default: the model's selector)."""
        return choose(scene, target, num_views)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        """The source views the model is given (default: unchanged). Images stay in [0, 1], ``[V, 3, H, W]``.

        Args:
            generator: seeded per (case, level, target view): the same suite gives the same perturbation.
        """
        return sources
