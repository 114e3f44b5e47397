"""Replica semantic classes and the 51-class map GP-NeRF and Semantic-Ray train on.

Sources (facts looked up, no code copied):

* Raw ids 0..101 and their names: the ``classes`` table of Replica's ``habitat/info_semantic.json`` (objects
  ``{"id": 1, "name": "backpack"}``, ``{"id": 2, "name": "base-cabinet"}``, ...), which Semantic-NeRF's Replica renders
  write into ``semantic_class_<i>.png``. The id -> name table was taken from two independent public copies of that
  table found with the code search (a ``replica_ids_to_classes`` dict and a ``REPLICA_CLASSES`` list); they agree on
  every id used here (one spells id 38 "excercise-ball", which is not one of the 51). Id 0 is unlabelled
  ("other" / "no_class").
* The 51 valid ids, in this order, mapped to 0..50: GP-NeRF ``gpnerf/data_loaders/replica_dataset.py``
  (``PointSegClassMapping(valid_cat_ids=[3, 7, 8, ..., 98], max_cat_id=101)``, repo ``lifuguan/GP-NeRF``), inherited
  from Semantic-Ray. Every other id, and anything above 101 (the reference clips to 101), is ignored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gpnerf_core import DataError

IGNORE_INDEX = 255
"""Label value of pixels whose raw id is not one of the 51 valid ids."""

MAX_RAW_ID = 101
"""Largest id in Replica's class table; larger values in a ``semantic_class`` PNG are not Replica classes."""

# Replica's info_semantic.json class table, indexed by raw id 0..101.
RAW_CLASS_NAMES: tuple[str, ...] = (
    "other", "backpack", "base-cabinet", "basket", "bathtub", "beam", "beanbag", "bed", "bench", "bike",
    "bin", "blanket", "blinds", "book", "bottle", "box", "bowl", "camera", "cabinet", "candle",
    "chair", "chopping-board", "clock", "cloth", "clothing", "coaster", "comforter", "computer-keyboard", "cup",
    "cushion", "curtain", "ceiling", "cooktop", "countertop", "desk", "desk-organizer", "desktop-computer", "door",
    "exercise-ball", "faucet", "floor", "handbag", "hair-dryer", "handrail", "indoor-plant", "knife-block",
    "kitchen-utensil", "lamp", "laptop", "major-appliance", "mat", "microwave", "monitor", "mouse", "nightstand",
    "pan", "panel", "paper-towel", "phone", "picture", "pillar", "pillow", "pipe", "plant-stand", "plate", "pot",
    "rack", "refrigerator", "remote-control", "scarf", "sculpture", "shelf", "shoe", "shower-stall", "sink",
    "small-appliance", "sofa", "stair", "stool", "switch", "table", "table-runner", "tablet", "tissue-paper",
    "toilet", "toothbrush", "towel", "tv-screen", "tv-stand", "umbrella", "utensil-holder", "vase", "vent", "wall",
    "wall-cabinet", "wall-plug", "wardrobe", "window", "rug", "logo", "bag", "set-of-clothing",
)

VALID_RAW_IDS: tuple[int, ...] = (
    3, 7, 8, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 22, 23, 26, 29, 31, 34, 35, 37, 40, 44, 47, 52,
    54, 56, 59, 60, 61, 62, 63, 64, 65, 70, 71, 76, 78, 79, 80, 82, 83, 87, 88, 91, 92, 93, 95, 97, 98,
)
"""Raw Replica ids of classes 0..50, in class order."""

CLASS_NAMES: tuple[str, ...] = tuple(RAW_CLASS_NAMES[i] for i in VALID_RAW_IDS)
"""Names of classes 0..50 (``basket``, ``bed``, ..., ``wall``, ``wall-plug``, ``window``, ``rug``)."""


def raw_to_class_table() -> np.ndarray:
    """``[MAX_RAW_ID + 1]`` int64: class id of each raw id, ``IGNORE_INDEX`` for the ids outside the 51."""
    table = np.full(MAX_RAW_ID + 1, IGNORE_INDEX, dtype=np.int64)
    table[list(VALID_RAW_IDS)] = np.arange(len(VALID_RAW_IDS))
    return table


_TABLE = torch.from_numpy(raw_to_class_table())


def map_raw_labels(raw: torch.Tensor, path: Path, *, strict: bool = True) -> torch.Tensor:
    """Map raw Replica ids to class ids 0..50 or ``IGNORE_INDEX``.

    Args:
        raw: ``[H, W]`` int64 raw ids as read from ``path``.
        path: the label file, named in errors.
        strict: raise on ids above ``MAX_RAW_ID``; False ignores them (the reference clips them to 101 = ignore).

    Raises:
        DataError: an id outside 0..101 with ``strict``.
    """
    unknown = (raw < 0) | (raw > MAX_RAW_ID)
    if bool(unknown.any()):
        if strict:
            ids = torch.unique(raw[unknown])[:5].tolist()
            raise DataError(
                f"{path}: label ids {ids} are not Replica class ids; expected 0..{MAX_RAW_ID} "
                "(Semantic-NeRF semantic_class renders; set dataset.strict_labels=false to ignore them)"
            )
        raw = raw.clamp(0, MAX_RAW_ID)
        mapped = _TABLE[raw]
        mapped[unknown] = IGNORE_INDEX
        return mapped
    return _TABLE[raw]
