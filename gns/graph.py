"""Graphs: mesh edges from triangles, and packing many object graphs into one batch.

Convention used everywhere in gns: an edge k goes from `senders[k]` to `receivers[k]`; its
message is summed at the receiver. Mesh edges come in both directions, so every undirected
mesh edge is two graph edges. A batch is one big graph whose nodes are the vertices of all its
objects, numbered graph after graph (node offset per graph); `node_graph[i]` names the graph of
node i. Further edge sets (collision edges between objects, later) are extra `EdgeSet` fields.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Directed edges of a triangle mesh, both directions, without duplicates.

    faces: (F, 3) vertex indices. Returns (E, 2) int64 [sender, receiver], sorted.
    """
    faces = np.asarray(faces, np.int64)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs = np.concatenate([pairs, pairs[:, ::-1]])
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0)


@dataclass
class EdgeSet:
    senders: torch.Tensor    # (E,) int64 node index
    receivers: torch.Tensor  # (E,) int64 node index

    def to(self, device) -> "EdgeSet":
        return EdgeSet(self.senders.to(device), self.receivers.to(device))


@dataclass
class Graph:
    """A packed batch of object graphs (one graph = one object in one window)."""

    mesh_edges: EdgeSet
    rest: torch.Tensor        # (N, 3) float64 scaled rest vertex, body frame (centre of mass at 0)
    material: torch.Tensor    # (N, 2) float32 friction, restitution of the node's object
    node_graph: torch.Tensor  # (N,) int64 graph index of each node
    num_graphs: int

    @property
    def num_nodes(self) -> int:
        return self.rest.shape[0]

    def to(self, device) -> "Graph":
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, value in moved.items():
            if isinstance(value, (torch.Tensor, EdgeSet)):
                moved[name] = value.to(device)
        return Graph(**moved)


def _ragged_arange(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For counts (B,): the owner (sum counts,) of each element and its index within its owner."""
    owner = torch.repeat_interleave(torch.arange(len(counts)), counts)
    starts = torch.cumsum(counts, 0) - counts
    return owner, torch.arange(int(counts.sum())) - starts[owner]


class MeshLibrary:
    """The dataset's rest meshes, stored once, from which batches of graphs are packed."""

    def __init__(self, meshes: dict[str, tuple[np.ndarray, np.ndarray]]):
        self.names = sorted(meshes)
        self.index = {name: i for i, name in enumerate(self.names)}
        verts = [np.asarray(meshes[n][0], np.float64) for n in self.names]
        edges = [mesh_edges(meshes[n][1]) for n in self.names]
        for name, v, e in zip(self.names, verts, edges):
            if len(e) and e.max() >= len(v):
                raise ValueError(f"mesh {name!r}: a face names vertex {e.max()}, it has {len(v)}")
        self.num_vertices = torch.tensor([len(v) for v in verts])
        self.num_edges = torch.tensor([len(e) for e in edges])
        self._vertex_start = torch.cumsum(self.num_vertices, 0) - self.num_vertices
        self._edge_start = torch.cumsum(self.num_edges, 0) - self.num_edges
        self._vertices = torch.from_numpy(np.concatenate(verts))
        self._edges = torch.from_numpy(np.concatenate(edges))

    def shape_ids(self, names: list[str]) -> torch.Tensor:
        missing = [n for n in names if n not in self.index]
        if missing:
            raise ValueError(f"shape {missing[0]!r} has no mesh; meshes: {', '.join(self.names)}")
        return torch.tensor([self.index[n] for n in names], dtype=torch.int64)

    def pack(self, shape_ids: torch.Tensor, scale: torch.Tensor, friction: torch.Tensor,
             restitution: torch.Tensor) -> Graph:
        """One graph per entry of shape_ids (B,), with per-graph scale, friction, restitution (B,)."""
        n_vert = self.num_vertices[shape_ids]
        node_graph, local = _ragged_arange(n_vert)
        library_node = self._vertex_start[shape_ids][node_graph] + local
        rest = self._vertices[library_node] * scale.to(torch.float64)[node_graph, None]

        n_edge = self.num_edges[shape_ids]
        edge_graph, local_edge = _ragged_arange(n_edge)
        library_edge = self._edge_start[shape_ids][edge_graph] + local_edge
        node_offset = torch.cumsum(n_vert, 0) - n_vert
        edges = self._edges[library_edge] + node_offset[edge_graph, None]

        material = torch.stack([friction, restitution], dim=1).to(torch.float32)[node_graph]
        return Graph(EdgeSet(edges[:, 0].contiguous(), edges[:, 1].contiguous()), rest, material,
                     node_graph, len(shape_ids))
