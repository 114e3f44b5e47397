"""torch.distributed for training and evaluation: the process group ``torchrun`` describes, and its collectives.

One process per device. ``torchrun`` sets ``RANK``, ``LOCAL_RANK`` and ``WORLD_SIZE`` (one node:
``--nproc_per_node=N``; several nodes: ``--nnodes`` and ``--rdzv-endpoint``); without them the run is a single
process and every collective below is the identity. The backend follows the device: NCCL on CUDA, gloo on CPU.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from gpnerf_core.runtime.device import resolve_device
from gpnerf_core.errors import ConfigError


@dataclass(frozen=True)
class Distributed:
    """This process's place in the job.

    Attributes:
        rank: global rank in ``[0, world_size)``; rank 0 alone writes the run folder.
        world_size: number of processes.
        local_rank: rank on this node (selects the CUDA device).
        device: this process's device.
    """

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @classmethod
    def single(cls, device: torch.device | str = "cpu") -> "Distributed":
        """One process on ``device`` (no process group)."""
        return cls(rank=0, world_size=1, local_rank=0, device=torch.device(device))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def backend(self) -> str | None:
        return dist.get_backend() if self.enabled else None

    def barrier(self) -> None:
        if self.enabled:
            dist.barrier()

    def all_reduce(self, tensor: Tensor, op: str = "sum") -> Tensor:
        """Reduce ``tensor`` in place across processes (``sum`` or ``max``) and return it."""
        if self.enabled:
            dist.all_reduce(tensor, op=dist.ReduceOp.SUM if op == "sum" else dist.ReduceOp.MAX)
        return tensor

    def all_gather_object(self, obj: Any) -> list[Any]:
        """Every process's ``obj``, in rank order (picklable objects)."""
        if not self.enabled:
            return [obj]
        gathered: list[Any] = [None] * self.world_size
        dist.all_gather_object(gathered, obj)
        return gathered

    def broadcast_object(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every process."""
        if not self.enabled:
            return obj
        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def shutdown(self) -> None:
        if self.enabled and dist.is_initialized():
            dist.destroy_process_group()


def launched_world_size() -> int:
    """WORLD_SIZE from the launcher's environment (1 without a launcher)."""
    try:
        return int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError:
        raise ConfigError(f"environment variable WORLD_SIZE={os.environ['WORLD_SIZE']!r} is not an integer") from None


def init_distributed(device_name: str) -> Distributed:
    """Join the process group the launcher describes (or return a single-process ``Distributed``).

    Sets the CUDA device of this process before the group is created, as NCCL requires.
    """
    world_size = launched_world_size()
    if world_size <= 1:
        return Distributed.single(resolve_device(device_name))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(device_name, local_rank, world_size)
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        kwargs: dict[str, Any] = {"device_id": device} if device.type == "cuda" else {}
        store = _attempt_store(world_size)
        if store is not None:
            kwargs["store"] = store
        dist.init_process_group(backend=backend, rank=rank, world_size=world_size, **kwargs)
    return Distributed(rank=rank, world_size=world_size, local_rank=local_rank, device=device)


def _attempt_store(world_size: int) -> dist.Store | None:
    """Under torchrun's agent store, a client of it whose keys are private to this restart attempt; else None
    (``env://`` as usual).

    torchrun (2.13) keeps one store across restarts of the worker group, so the processes of a restarted group would
    read the addresses the dead group published and fail to connect ("Connection refused"). Prefixing the keys by
    ``TORCHELASTIC_RESTART_COUNT`` gives each attempt its own.
    """
    if os.environ.get("TORCHELASTIC_USE_AGENT_STORE") != "True" or "TORCHELASTIC_RESTART_COUNT" not in os.environ:
        return None
    from datetime import timedelta

    client = dist.TCPStore(
        host_name=os.environ["MASTER_ADDR"], port=int(os.environ["MASTER_PORT"]), world_size=world_size,
        is_master=False, timeout=timedelta(minutes=10),
    )
    return dist.PrefixStore(f"gpnerf/attempt_{os.environ['TORCHELASTIC_RESTART_COUNT']}", client)
