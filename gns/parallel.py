"""Training on several processes (torchrun): who this process is, and sums over all of them.

`torchrun --nproc_per_node P -m gns.cli train ...` starts P copies of the same training; each
finds WORLD_SIZE, RANK and LOCAL_RANK in its environment. With WORLD_SIZE > 1 `gns.train`
joins a process group (gloo on the CPU, nccl on CUDA) and every process takes a contiguous
share of the same global batch (`share`). In one process every function here is the identity,
so single-process training runs exactly the code it ran before.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from gns.config import ConfigError


@dataclass(frozen=True)
class World:
    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """The process that writes checkpoints, metrics and logs."""
        return self.rank == 0


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name, str(default))
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f"environment variable {name}={value!r} is not an integer (set by torchrun)") from None


def world_from_env() -> World:
    """This process's place among the torchrun processes (one process when not launched by torchrun)."""
    return World(_env_int("RANK", 0), _env_int("WORLD_SIZE", 1), _env_int("LOCAL_RANK", 0))


def start(world: World, device: torch.device) -> None:
    """Join the process group of a multi-process run (nothing to do in one process)."""
    if world.size > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")


def stop(world: World, together: bool = True) -> None:
    """Leave the process group; `together` (after a finished training) waits for every process
    first, since rank 0 hosts the group's store. A process leaving on an error does not wait
    for the others, which may never get there: torchrun stops them when it exits."""
    if world.size > 1 and dist.is_initialized():
        if together:
            dist.barrier()
        dist.destroy_process_group()


def active() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def sum_over_processes(t: torch.Tensor) -> torch.Tensor:
    """t summed over every process of the run; t itself in one process."""
    if not active():
        return t
    t = t.clone()
    dist.all_reduce(t)
    return t


def share(batch_size: int, world: World) -> tuple[int, int]:
    """The windows [lo, hi) of a global batch that this process trains on: contiguous, disjoint,
    sizes differing by at most one."""
    return batch_size * world.rank // world.size, batch_size * (world.rank + 1) // world.size
