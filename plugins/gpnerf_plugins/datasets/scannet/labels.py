"""ScanNet label ids -> the 20 classes of the ScanNet benchmark, through ``scannetv2-labels.combined.tsv``.

A ``label-filt/<f>.png`` pixel holds a raw ScanNet category id (the tsv's ``id`` column; 0 = unannotated). The
tsv maps it to an NYU40 id (column ``nyu40id``), and the benchmark keeps 20 NYU40 ids (ScanNet's
``VALID_CLASS_IDS``), numbered 0..19 here in that order. Everything else, 0 included, is ``IGNORE_INDEX``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpnerf_plugins.datasets.scannet.files import LayoutError

LABEL_MAP_NAME = "scannetv2-labels.combined.tsv"
LABEL_MAP_SOURCE = (
    "it ships with the ScanNet release: fetch it with ScanNet's download-scannet.py --label_map, "
    "or set dataset.label_map_file"
)

SCANNET20_NYU40_IDS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)
SCANNET20_CLASS_NAMES: tuple[str, ...] = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "desk", "curtain", "refrigerator", "shower curtain", "toilet", "sink", "bathtub",
    "otherfurniture",
)  # fmt: skip
IGNORE_INDEX = 255
UNKNOWN = -1
"""Lookup value of raw ids absent from the tsv (mapped to ``IGNORE_INDEX`` with a warning)."""


def nyu40_to_scannet20() -> np.ndarray:
    """``[41]`` int64: class id 0..19 of each NYU40 id 0..40, ``IGNORE_INDEX`` for the 21 ids not benchmarked."""
    table = np.full(41, IGNORE_INDEX, dtype=np.int64)
    table[list(SCANNET20_NYU40_IDS)] = np.arange(len(SCANNET20_NYU40_IDS))
    return table


@dataclass(frozen=True)
class LabelMap:
    """Raw ScanNet id -> ScanNet-20 class.

    Attributes:
        path: the tsv it was read from.
        lookup: ``[max_id + 1]`` int64; ``lookup[raw]`` is a class 0..19, ``IGNORE_INDEX``, or ``UNKNOWN`` for
            ids the tsv does not list (0, unannotated, maps to ``IGNORE_INDEX``).
    """

    path: Path
    lookup: np.ndarray

    def apply(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Map a raw label image.

        Args:
            raw: ``[H, W]`` non-negative integer ids.

        Returns:
            ``(labels [H, W] int64, unknown ids (sorted, int64), number of unknown pixels)``; unknown pixels
            are ``IGNORE_INDEX`` in ``labels``.
        """
        raw = raw.astype(np.int64, copy=False)
        inside = raw < len(self.lookup)
        mapped = np.full(raw.shape, UNKNOWN, dtype=np.int64)
        mapped[inside] = self.lookup[raw[inside]]
        unknown = mapped == UNKNOWN
        count = int(unknown.sum())
        if not count:
            return mapped, np.zeros(0, dtype=np.int64), 0
        mapped[unknown] = IGNORE_INDEX
        return mapped, np.unique(raw[unknown]), count


_EXPECTED = "ScanNet's tab-separated label map (header row with columns 'id' and 'nyu40id', one integer row per id)"


def _int_cell(value: str, path: Path, line: int, column: str) -> int:
    try:
        return int(value.strip())
    except ValueError:
        raise LayoutError(f"{path}:{line}", f"an integer in column {column!r}", repr(value)) from None


def read_label_map(path: str | Path) -> LabelMap:
    """Read ``scannetv2-labels.combined.tsv`` (tab-separated, header row; columns found by the names ``id`` and
    ``nyu40id``).

    Raises:
        LayoutError (a DataError): the file is missing or unreadable, a column is absent, a value is not an integer,
            an NYU40 id is outside 0..40, or a raw id is listed twice.
    """
    path = Path(path)
    if not path.is_file():
        raise LayoutError(path, f"ScanNet's label map {LABEL_MAP_NAME} ({LABEL_MAP_SOURCE})", "nothing")
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = list(csv.reader(handle, delimiter="\t"))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise LayoutError(path, _EXPECTED, f"an unreadable file ({type(exc).__name__}: {exc})") from None
    if not rows:
        raise LayoutError(path, _EXPECTED, "an empty file")
    header = [cell.strip() for cell in rows[0]]
    missing = [name for name in ("id", "nyu40id") if name not in header]
    if missing:
        shown = ", ".join(header[:6]) + (", ..." if len(header) > 6 else "")
        raise LayoutError(f"{path}:1", f"a header column {missing[0]!r}", f"columns {shown}")
    id_col, nyu_col = header.index("id"), header.index("nyu40id")
    pairs: dict[int, int] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) <= max(id_col, nyu_col):
            raise LayoutError(f"{path}:{line}", f"at least {max(id_col, nyu_col) + 1} columns", f"{len(row)}")
        raw = _int_cell(row[id_col], path, line, "id")
        nyu = _int_cell(row[nyu_col], path, line, "nyu40id")
        if raw < 0:
            raise LayoutError(f"{path}:{line}", "a non-negative ScanNet category id", f"id {raw}")
        if not 0 <= nyu <= 40:
            raise LayoutError(f"{path}:{line}", "an NYU40 id in 0..40", f"nyu40id {nyu}")
        if raw in pairs:
            raise LayoutError(f"{path}:{line}", "each id listed once", f"id {raw} again")
        pairs[raw] = nyu
    if not pairs:
        raise LayoutError(path, _EXPECTED, "no rows after the header")
    lookup = np.full(max(pairs) + 1, UNKNOWN, dtype=np.int64)
    lookup[0] = IGNORE_INDEX
    to20 = nyu40_to_scannet20()
    ids = np.fromiter(pairs.keys(), dtype=np.int64)
    lookup[ids] = to20[np.fromiter(pairs.values(), dtype=np.int64)]
    return LabelMap(path=path, lookup=lookup)
