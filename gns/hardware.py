"""Where the network runs: which torch device (checked before any work), how many processes
share a training (torchrun), and whether bfloat16 autocast pays on this machine.

bfloat16 pays on some CPUs and costs on others with the same instruction-set flags: on one AMD
EPYC (avx512_bf16) bf16 + compile trained `gns_cpu` 1.76x as fast as float32; on an Intel
Xeon (avx512_bf16, no AMX) a bf16 matrix product of the network's shapes
ran 1.8x slower than float32 (experiments/log.md). No flag tells them apart, so `auto` times one
such product in both types, once per process and shape, and picks bf16 only when it is clearly
faster. Off a CPU (CUDA) `auto` takes bf16 where the device supports it.
"""
from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from typing import Callable

import torch
import torch.distributed as dist

from gns.config import ConfigError

CHOICES = ("none", "bf16", "auto")
# bf16 must be this much faster: autocast adds casts that the product alone does not show
MARGIN = 1.15
# bf16 asked for by name but this much slower than float32 earns a warning: a CPU without native
# bfloat16 emulates it (an AMD EPYC without avx512: rollouts 12-14x slower), where `auto`
# would have kept float32
SLOW = 0.5
_cache: dict[tuple, float] = {}


def bf16_speedup(width: int, rows: int = 4096, repeats: int = 5, device: str | torch.device = "cpu") -> float:
    """float32 time / bfloat16 time of a (rows, 3 width) x (3 width, width) matrix product, the
    shape of the network's first edge layer (best of `repeats`, each several products);
    cached per (width, rows, device, threads)."""
    device = torch.device(device)
    key = (width, rows, str(device), torch.get_num_threads())
    if key not in _cache:
        a = torch.randn(rows, 3 * width, device=device)
        w = torch.randn(3 * width, width, device=device)
        times = {}
        for dtype in (torch.float32, torch.bfloat16):
            x, y = a.to(dtype), w.to(dtype)
            x @ y  # warm-up: first-call costs are not the product's
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                for _ in range(4):
                    x @ y
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                best = min(best, time.perf_counter() - t0)
            times[dtype] = best
        _cache[key] = times[torch.float32] / times[torch.bfloat16]
    return _cache[key]


def resolve_autocast(name: str, width: int, device: str | torch.device = "cpu", measure=bf16_speedup) -> str:
    """'none' or 'bf16' for `name` ('none', 'bf16' or 'auto'); 'auto' measures (measure(width,
    device=...) -> float32 / bf16 time) and takes bf16 when it is at least MARGIN times faster.
    'bf16' on a CPU is kept but measured too, with a warning where it is less than SLOW times as fast."""
    if name not in CHOICES:
        raise ValueError(f"autocast must be one of {', '.join(CHOICES)}, got {name!r}")
    device = torch.device(device)
    if name == "bf16" and device.type == "cpu":
        ratio = measure(width, device=device)
        if ratio < SLOW:
            warnings.warn(f"bf16 autocast measures {1 / ratio:.0f}x slower than float32 on this CPU (no native "
                          "bfloat16): --autocast auto would keep float32 here", stacklevel=2)
    if name != "auto":
        return name
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "none"
    return "bf16" if measure(width, device=device) >= MARGIN else "none"


def parse_device(name: str, what: str = "train.device") -> torch.device:
    """A device name as a torch device, checked before any work: one line, not torch's assertion."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"{what}={name!r} is not a torch device; use 'cpu' or 'cuda'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{what}={name} but CUDA is not available in this torch build "
                          f"(torch {torch.__version__}); use {what}=cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(f"{what}={name} but this machine has {torch.cuda.device_count()} CUDA device(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"{what}={name} but MPS is not available here; use {what}=cpu")
    if device.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{what}={name}: only cpu, cuda and mps are supported")
    return device


# Training on several processes (torchrun): who this process is, and sums over all of them.
#
# `torchrun --nproc_per_node P -m gns.cli train ...` starts P copies of the same training; each
# finds WORLD_SIZE, RANK and LOCAL_RANK in its environment. With WORLD_SIZE > 1 `gns.train`
# joins a process group (gloo on the CPU, nccl on CUDA) and every process takes a contiguous
# share of the same global batch (`share`). In one process every function here is the identity,
# so single-process training runs exactly the code it ran before.


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


def training_device(name: str, world: World = World()) -> torch.device:
    device = parse_device(name)
    if world.size > 1 and device.type == "cuda":
        return torch.device("cuda", world.local_rank)  # torchrun: one GPU per process
    if world.size > 1 and device.type == "mps":
        raise ConfigError("training on several processes runs on cpu or cuda, not mps")
    return device


def set_threads(threads: int, log: Callable[[str], None]) -> None:
    """Use `threads` (0 = all cores), warning when other processes already load the cores:
    OpenMP threads that get descheduled stall every parallel region (measured: 16 -> 0.6 steps/s)."""
    cores = os.cpu_count() or 1
    threads = threads or cores
    torch.set_num_threads(threads)
    load = os.getloadavg()[0]
    if threads > 1 and load + threads > cores + 0.5:
        log(f"warning: {threads} threads on {cores} cores with a load average of {load:.1f}; "
            f"if steps/s collapse, use --set train.threads=1")
