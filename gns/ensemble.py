"""Ensembles (the rollout option `ensemble`): other models whose predictions every step averages
with the model's. They must read the graphs the model reads, which is checked once when they are
loaded; a member that differs only in features.surface_edges reads each step's graph with its own
mesh edges, rebuilt here. Loaded only for a model with an ensemble.
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Sequence

import torch

from gns.graph import EdgeSet, GraphBatch, mesh_edges

if TYPE_CHECKING:
    from gns.simulator import LearnedSimulator


def _listed(t: torch.Tensor | None) -> list | None:
    """A small tensor as a list, for comparisons and messages."""
    return None if t is None else [round(float(v), 12) for v in t.reshape(-1)]


def _surface_free(settings: dict, other: LearnedSimulator) -> dict:
    """Graph settings as an ensemble compares them: surface_edges left out where both models have
    centre nodes (the spokes are then rebuilt exactly)."""
    if settings["centre_node"] and other._graph_settings["centre_node"]:
        return {k: v for k, v in settings.items() if k != "surface_edges"}
    return settings


def check_members(model: LearnedSimulator, members: Sequence[LearnedSimulator], role: str = "ensemble member") -> None:
    """ValueError naming the first member that reads other graphs than `model`: another network
    mesh, floor, collision edges, time step or nodes seen (LearnedSimulator.set_ensemble, and
    set_contact_model with `role` "contact network")."""
    for k, m in enumerate(members, 1):
        for what, mine, theirs in (("network mesh (features.centre_node, surface_edges)",
                                    _surface_free(model._graph_settings, m), _surface_free(m._graph_settings, model)),
                                   ("floor height", model.layout.floor_z, m.layout.floor_z),
                                   ("collision edges (features and radius)",
                                    (model.layout.collision_groups, model.layout.collision_radius),
                                    (m.layout.collision_groups, m.layout.collision_radius)),
                                   ("time step and gravity", _listed(model.gravity_per_frame),
                                    _listed(m.gravity_per_frame)),
                                   ("nodes seen (features.lowest_vertices, highest_vertices)",
                                    (model.lowest_vertices, model.highest_vertices),
                                    (m.lowest_vertices, m.highest_vertices))):
            if mine != theirs:
                who = f"{role} {k}" if role == "ensemble member" else role
                raise ValueError(f"{who} differs from the model in its {what}: "
                                 f"{theirs} there, {mine} in the model")


def with_surface_edges(graph: GraphBatch, surface: bool) -> GraphBatch:
    """A graph with centre nodes (the last node of each graph, MeshLibrary's centre_node) with its
    mesh edges rebuilt from its faces: the surface edges (if `surface`) and the spokes, in the
    order MeshLibrary packs them, so that a model trained on the other kind of graph
    (features.surface_edges) reads the same nodes (an ensemble member)."""
    if graph.faces is None:
        raise ValueError("the graph has no faces to rebuild its surface edges from")
    g = graph.num_graphs
    device = graph.node_graph.device
    count = torch.bincount(graph.node_graph, minlength=g)
    centre = torch.cumsum(count, 0) - 1
    ring = torch.ones(graph.num_nodes, dtype=torch.bool, device=device)
    ring[centre] = False
    ring = ring.nonzero()[:, 0]
    hub = centre[graph.node_graph[ring]]
    parts = [torch.stack([ring, hub], 1), torch.stack([hub, ring], 1)]
    kinds = [1, 2]
    if surface:   # the batch's node numbers keep each graph's edges together and sorted as its own
        parts.insert(0, torch.from_numpy(mesh_edges(graph.faces.cpu().numpy())).to(device))
        kinds.insert(0, 0)
    edges = torch.cat(parts)
    kind = torch.cat([torch.full((len(p),), k, device=device) for p, k in zip(parts, kinds)])
    # graph by graph, and within a graph surface edges, then spokes in, then spokes out
    order = torch.sort(graph.node_graph[edges[:, 0]] * 3 + kind, stable=True).indices
    edges = edges[order]
    return replace(graph, mesh_edges=EdgeSet(edges[:, 0].contiguous(), edges[:, 1].contiguous()))
