"""Point clouds as binary little-endian PLY (the format Open3D, MeshLab, CloudCompare, trimesh and viser's loaders
read): one ``vertex`` element whose properties are the given columns, written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gpnerf_core.runtime.io import atomic_write_bytes

PLY_TYPES = {
    np.dtype("float32"): "float", np.dtype("float64"): "double", np.dtype("uint8"): "uchar",
    np.dtype("int8"): "char", np.dtype("uint16"): "ushort", np.dtype("int16"): "short",
    np.dtype("uint32"): "uint", np.dtype("int32"): "int",
}
"""numpy dtypes PLY has a type for, and its name for each."""


def encode_ply(columns: dict[str, np.ndarray], comments: tuple[str, ...] = ()) -> bytes:
    """The bytes of a PLY file with one ``vertex`` element.

    Args:
        columns: property name -> ``[N]`` array, in file order; conventional names are ``x y z`` (float),
            ``red green blue`` (uchar) and ``nx ny nz``; others are kept as extra properties, which readers that
            do not know them pass over.
        comments: ``comment`` lines of the header (no newlines).

    Raises:
        ValueError: columns of different lengths, a dtype PLY has no type for, or a comment with a newline.
    """
    lengths = {name: len(values) for name, values in columns.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"PLY columns differ in length: {lengths}")
    count = next(iter(lengths.values()), 0)
    header = ["ply", "format binary_little_endian 1.0"]
    for comment in comments:
        if "\n" in comment or "\r" in comment:
            raise ValueError(f"PLY comment {comment!r} holds a line break")
        header.append(f"comment {comment}")
    header.append(f"element vertex {count}")
    fields = []
    for name, values in columns.items():
        dtype = np.asarray(values).dtype
        if dtype not in PLY_TYPES:
            raise ValueError(f"PLY column {name!r} has dtype {dtype}; expected one of {sorted(map(str, PLY_TYPES))}")
        header.append(f"property {PLY_TYPES[dtype]} {name}")
        fields.append((name, dtype.newbyteorder("<")))
    header.append("end_header")
    records = np.empty(count, dtype=fields)
    for name, values in columns.items():
        records[name] = values
    return ("\n".join(header) + "\n").encode("ascii") + records.tobytes()


def write_ply(path: str | os.PathLike[str], columns: dict[str, np.ndarray], comments: tuple[str, ...] = ()) -> Path:
    """``encode_ply`` written atomically to ``path``; returns the path."""
    return atomic_write_bytes(path, encode_ply(columns, comments))
