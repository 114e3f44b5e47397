"""A binary PLY read from the format alone (no project code): what a splat viewer does with an export."""

from __future__ import annotations

import numpy as np


def read_ply(data: bytes) -> dict[str, np.ndarray]:
    """A binary little-endian PLY's vertex properties, read from the format alone (no project code)."""
    header, _, body = data.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    types = {"float": "<f4", "int": "<i4", "uchar": "u1"}
    fields = [(line.split()[2], types[line.split()[1]]) for line in lines if line.startswith("property")]
    records = np.frombuffer(body, dtype=np.dtype(fields), count=count)
    return {name: records[name].copy() for name, _ in fields}
