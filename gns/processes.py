"""Training on several processes (torchrun): the process group, each process's share of a global
batch, the network wrapped to average gradients, and sums over the processes.

`torchrun --nproc_per_node P -m gns.cli train ...` starts P copies of the same training; each
finds WORLD_SIZE, RANK and LOCAL_RANK in its environment (gns.run_folder.world_from_env). With
WORLD_SIZE > 1 `gns.train` joins a process group (gloo on the CPU, nccl on CUDA) and every
process takes a contiguous share of the same global batch (`share`). Only such a training loads
this module, so a training in one process runs exactly the code it ran before there were several.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.distributed as dist

from gns.data import Batch
from gns.graph import EdgeSet, GraphBatch

if TYPE_CHECKING:
    from gns.run_folder import World


def start(world: World, device: torch.device) -> None:
    """Join the process group of a multi-process run."""
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


def distributed(network: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """The network wrapped to average its gradients over the processes (DistributedDataParallel)."""
    from torch.nn.parallel import DistributedDataParallel
    return DistributedDataParallel(network, device_ids=[device.index] if device.type == "cuda" else None)


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


def windows(batch: Batch, lo: int, hi: int) -> Batch:
    """The windows [lo, hi) of a batch (its graphs of scenes lo .. hi-1), renumbered: this
    process's share of a global batch (`share`)."""
    g = batch.graph
    keep_graph = (g.graph_scene >= lo) & (g.graph_scene < hi)
    keep = keep_graph[g.node_graph]
    new_node = torch.cumsum(keep, 0) - 1                   # new index of each kept node
    new_graph = torch.cumsum(keep_graph, 0) - 1
    edges = keep[g.mesh_edges.senders]                     # mesh edges stay inside one graph
    faces = None if g.faces is None else new_node[g.faces[keep[g.faces[:, 0]]]]
    graph = GraphBatch(EdgeSet(new_node[g.mesh_edges.senders[edges]], new_node[g.mesh_edges.receivers[edges]]),
                       g.rest[keep], g.material[keep], new_graph[g.node_graph[keep]], int(keep_graph.sum()),
                       g.graph_scene[keep_graph] - lo, None, faces,
                       symmetries=None if g.symmetries is None else g.symmetries[keep_graph],
                       num_symmetries=None if g.num_symmetries is None else g.num_symmetries[keep_graph])
    future = None if batch.future is None else batch.future[keep]
    return Batch(batch.history[keep], batch.target[keep], graph, future)
