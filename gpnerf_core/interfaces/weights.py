"""Optional interface of components that can start from another code base's checkpoint (GNT's, ...)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from torch import Tensor


@dataclass(frozen=True)
class ImportedWeights:
    """A component's (or a whole model's) share of a foreign checkpoint.

    Attributes:
        tensors: ``{key in the component's own state dict: (key in the checkpoint, tensor)}``; the checkpoint
            key is dotted from the checkpoint's top level (``net_coarse.q_fcs.0.0.weight``) so reports name it.
        format: the checkpoint's format (``gnt``), for the report; a model's ``read_foreign`` sets it.
        offered: every weight key of the checkpoint (dotted), so the keys no part took are reported; a model's
            ``read_foreign`` sets it.
        ignored: top-level entries of the checkpoint left out on purpose (optimizer state, ...).
    """

    tensors: dict[str, tuple[str, Tensor]]
    format: str = ""
    offered: tuple[str, ...] = ()
    ignored: tuple[str, ...] = ()


class ImportsWeights:
    """Mixin of every model component: ``import_weights`` maps a foreign checkpoint onto the component.

    The default supports no format. ``model.init=<file>`` hands a foreign checkpoint to the model family
    (``ModelFamily.read_foreign``), which asks its components for their shares (the ``gnt`` family calls this on its
    extractor, aggregators and head); the core checks names and shapes against the model's state dict and reports what
    was loaded, what the model still lacks and what no component took.
    """

    def import_weights(self, checkpoint: Mapping[str, Any], fmt: str) -> ImportedWeights | None:
        """Map ``checkpoint`` (format ``fmt``, e.g. ``"gnt"``) onto this component; None when unsupported."""
        return None
