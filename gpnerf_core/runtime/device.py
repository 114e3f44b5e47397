"""Devices: which one a process uses, what it has used, and the precision the forward pass runs in."""

from __future__ import annotations

import contextlib
import resource
from typing import ContextManager

import torch

from gpnerf_core.errors import ConfigError

PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}
"""``train.precision`` values and the autocast dtype each selects (None: no autocast)."""


def resolve_device(name: str, local_rank: int = 0, world_size: int = 1) -> torch.device:
    """The device for ``device=<name>``: ``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:N``.

    Under a multi-process launch each process takes ``cuda:<local_rank>``, so ``cuda:N`` is refused there.
    """
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"device={name!r} is not a torch device; expected auto, cpu or cuda[:N]") from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={name!r}: gpnerf-core runs on cpu or cuda; expected auto, cpu or cuda[:N]")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device={name!r} but CUDA is not available; use device=cpu or device=auto")
        if world_size > 1:
            if device.index is not None:
                raise ConfigError(
                    f"device={name!r} under a {world_size}-process launch: use device=cuda (or auto); "
                    "each process takes the GPU of its LOCAL_RANK"
                )
            if local_rank >= torch.cuda.device_count():
                raise ConfigError(
                    f"LOCAL_RANK={local_rank} but this node has {torch.cuda.device_count()} GPUs; "
                    "start at most one process per GPU (--nproc_per_node)"
                )
            device = torch.device("cuda", local_rank)
        elif device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
    return device


def peak_memory_mb(device: torch.device) -> float:
    """Peak resident memory of this process (CPU) or peak allocated memory on ``device`` (CUDA), in MiB."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def check_precision(precision: str) -> None:
    if precision not in PRECISIONS:
        raise ConfigError(f"train.precision={precision!r}: expected one of {', '.join(PRECISIONS)}")


def autocast(device: torch.device, precision: str) -> ContextManager:
    """The autocast context of ``precision`` on ``device`` (a no-op for fp32)."""
    check_precision(precision)
    dtype = PRECISIONS[precision]
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def cpu_model() -> str:
    """The CPU's model name: /proc/cpuinfo's first ``model name`` on Linux, else what ``platform`` knows."""
    import platform

    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as cpuinfo:
            for line in cpuinfo:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, object]:
    """What a run's figures were measured on (``metrics.json``'s ``machine``): platform, CPU model (figures move
    between CPU models of one machine type), CPU count, torch threads and the CUDA device's name (None without one)."""
    import os
    import platform

    return {
        "platform": platform.platform(),
        "processor": platform.machine(),
        "cpu_model": cpu_model(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def checked_compile_backend(backend: str) -> str:
    """``backend`` if ``torch.compile`` knows it; otherwise a ConfigError naming the key and the known ones."""
    import torch._dynamo

    known = sorted(torch._dynamo.list_backends(exclude_tags=()))
    if backend not in known:
        raise ConfigError(f"model.compile_backend={backend!r} is not a torch.compile backend; known: {', '.join(known)}")
    return backend
