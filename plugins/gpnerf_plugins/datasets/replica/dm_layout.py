"""Reader of one scene in the DM-NeRF Replica layout (GP-NeRF's "Replica_DM").

A scene folder holds (no ``Sequence_<n>`` level)::

    rgb/rgb_<i>.png                              uint8 RGB(A)
    depth/depth_<i>.png                          uint16, millimetres (0 = unknown)
    semantic_instance/semantic_instance_<i>.png  raw instance ids, kept as they are
    semantic_class/semantic_class_<i>.png        optional: raw Replica class ids
    traj_w_c.txt                                 one row of 16 numbers per frame: row-major 4x4 camera-to-world,
                                                 OpenCV convention, metres

Frames are numbered ``i = 0 .. N-1`` with N the number of poses, and pose row ``i`` belongs to frame ``i``
(the reference builds the file names from ``range(N)``). The camera is Semantic-NeRF's (90 degree horizontal field
of view, centred principal point), derived at the loaded resolution.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gpnerf_core import DataError
from gpnerf_plugins.datasets.replica.layout import RGB_DIR, ReplicaSequence


class InstanceSequence(ReplicaSequence):
    """One DM-NeRF-layout scene: a ``ReplicaSequence`` whose ``semantic_instance`` files are required, whose
    ``semantic_class`` folder is optional (``Frame.semantic`` all ``ignore_index`` without it) and whose frames must
    be numbered ``0..N-1``.

    Args:
        path: the scene folder (``.../office_0``).
        options: ``hfov_deg``, ``size``, ``label_map``, ``ignore_index`` of ``ReplicaSequence``.

    Raises:
        DataError: a missing or malformed file, named in the message.
    """

    folder_kind = "scene"

    def __init__(self, path: str | Path, **options: Any) -> None:
        super().__init__(path, require_semantic=False, require_instance=True, **options)
        numbers = [files.number for files in self.files]
        if numbers != list(range(len(numbers))):  # as many frames as poses, so some number below N is missing
            missing = self.path / RGB_DIR / f"rgb_{min(set(range(len(numbers))) - set(numbers))}.png"
            raise DataError(f"{missing}: missing; expected frames numbered 0..{len(numbers) - 1}, one per pose")
