"""Interface of perception heads that decode an image-level semantic feature map."""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from typing import ClassVar

from torch import Tensor, nn

from gpnerf_core.interfaces.weights import ImportsWeights
from gpnerf_core.types import HeadOutput


class Predicts(str, enum.Enum):
    """What per-pixel scores are (a head's ``predicts``, a loss set's ``head_predicts``, a model's semantic output).

    A string enum: a plugin may write ``predicts = "instances"``; the core compares members."""

    CLASSES = "classes"
    """Logits over the dataset's classes: cross-entropy, mIoU and the segmentation protocols."""
    INSTANCES = "instances"
    """``slots + 1`` logits whose softmax assigns each pixel to an instance slot (the last: no instance): Hungarian-
    matched losses, instance AP."""


class PerceptionHead(ImportsWeights, nn.Module, ABC):
    """Turns a ``[N, C_sem, h, w]`` feature map into per-pixel scores.

    Constructed with ``in_dim`` (C_sem), ``in_levels`` (equal channel blocks, finest first) and
    ``num_outputs``, all supplied by the pipeline. ``num_outputs`` is the dataset's class count for a head that
    predicts classes; an instance head (``predicts = Predicts.INSTANCES``) has a ``slots`` option in its config and gets
    ``num_outputs = slots + 1`` (the last channel is "no instance").
    """

    predicts: ClassVar[Predicts] = Predicts.CLASSES
    """What its logits are (``Predicts``)."""

    @property
    @abstractmethod
    def num_outputs(self) -> int:
        """K: channels of ``HeadOutput.logits``."""

    @abstractmethod
    def forward(self, features: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """Decode ``features`` and return logits ``[N, K, *output_size]``."""
