"""The classes a model predicts, carried explicitly from the dataset (or a checkpoint) to the model, its checkpoints,
evaluation, rendering and the viewer."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from gpnerf_core.errors import DataError


@dataclass(frozen=True)
class ClassList:
    """The classes a model's head predicts.

    Attributes:
        names: names of the class ids 0..K-1.
        ignore_index: the label value of unlabelled pixels in the labels the model was trained on.
        source: where the list came from, for notes (``"dataset 'embedded'"``, ``"checkpoint <path>"``).
        from_checkpoint: the list is a checkpoint's (the dataset has none).
    """

    names: tuple[str, ...]
    ignore_index: int
    source: str = "dataset"
    from_checkpoint: bool = False

    @property
    def num_classes(self) -> int:
        return len(self.names)

    def describe(self, shown: int = 6) -> str:
        """``9 classes of checkpoint <path> (wall, floor, ..., 3 more)``, for notes."""
        more = len(self.names) - shown
        names = ", ".join(self.names[:shown]) + (f", ... {more} more" if more > 0 else "")
        return f"{self.num_classes} classes of {self.source} ({names})"

    def note(self, dataset: str) -> str:
        """What a command says when dataset ``dataset`` has no class list and these (a checkpoint's) are used."""
        return f"dataset {dataset!r} has no class list: using the {self.describe()}"


def stored_classes(state: Mapping[str, Any], path: str | Path) -> tuple[tuple[str, ...], int] | None:
    """The class names and ignore index a checkpoint's model was trained with, or None when it stores none (written
    before checkpoints kept them, or by a model trained without classes).

    Raises:
        DataError: the stored values are not a list of names and an integer.
    """
    names, ignore = state.get("class_names"), state.get("ignore_index")
    if names is None or (isinstance(names, (list, tuple)) and not names):
        return None
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise DataError(f"checkpoint {path}: class_names is {names!r:.80}; expected a list of class names")
    if not isinstance(ignore, int) or isinstance(ignore, bool):
        raise DataError(f"checkpoint {path}: ignore_index is {ignore!r}; expected an integer")
    return tuple(names), int(ignore)


def checkpoint_classes(state: Mapping[str, Any], path: str | Path) -> ClassList | None:
    """The classes a checkpoint stores (``stored_classes``) as a class list for a dataset without one; None for a
    checkpoint written before checkpoints kept them."""
    stored = stored_classes(state, path)
    return None if stored is None else ClassList(*stored, source=f"checkpoint {path}", from_checkpoint=True)
