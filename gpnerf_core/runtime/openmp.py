"""OpenMP's wait policy, set before torch loads its OpenMP runtime (``import gpnerf_core`` calls ``passive_wait``).

torch's CPU operators run on GNU OpenMP (libgomp), whose idle workers spin after each parallel region by default;
the numba rasterizer's tiles run on a thread pool of their own (``geometry.gaussians.numba_backend``). On this
project's 2-core machines, shared with other runs, the spinning workers took the cores from that pool and from the
other processes: the refinement step (``bench refine=50000``, semantic 3DGS at 96 x 128) at 2 threads took 4.3 s
median against 0.24 s with ``OMP_WAIT_POLICY=PASSIVE`` (docs/benchmarks.md, "Refinement step"). A passive worker
sleeps until the next parallel region: the same work split the same way, so every result is the same bit for bit;
only the wake-up of an idle worker costs more (a few microseconds per parallel region).

An ``OMP_WAIT_POLICY`` already in the environment is kept; ``GPNERF_OMP_PASSIVE=0`` leaves libgomp's default. Either
takes effect only when this runs before torch is first imported in the process (as ``python -m gpnerf_core`` does).
"""

from __future__ import annotations

import os

SWITCH = "GPNERF_OMP_PASSIVE"
"""``0``: leave OpenMP's wait policy to its default (spin, then sleep)."""


def passive_wait(environ: dict[str, str] | None = None) -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` in ``environ`` (``os.environ``) unless a policy is set or ``GPNERF_OMP_PASSIVE``
    is ``0``; whether it set it."""
    environ = os.environ if environ is None else environ
    if "OMP_WAIT_POLICY" in environ or environ.get(SWITCH, "1").strip() == "0":
        return False
    environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True
