"""A contact network: a second network of a model with collision edges, for the objects in contact.

Every step, the objects that send or receive a collision edge (and so their partners) are rolled
out by the contact network, every other object by the model's own network, each on its own part
of the batch. A collision edge always joins two objects in contact, so the cut loses no edge;
each object goes through one network, and an object that meets no other rolls out exactly as the
model alone rolls it out. So the model can keep single-object weights fixed (train.collisions_only)
while the contact network trains every weight on collisions: trained alone, that network is
worse on floor contacts and in flight, better where objects meet (experiments/log.md, 2026-12-07).
Attached by LearnedSimulator.set_contact_model; shipped inside an exported model
(gns.zoo.export_model's `contact`, gns.checkpoint.CONTACT).
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from gns.graph import GraphBatch, select_graphs

if TYPE_CHECKING:
    from gns.simulator import LearnedSimulator


def check_contact(model: LearnedSimulator, contact: LearnedSimulator) -> None:
    """ValueError (one line) unless `contact` reads the very graphs `model` reads: unlike an
    ensemble member's, its graphs are not rebuilt for it."""
    if not model.layout.collisions:
        raise ValueError("a contact network needs a model with collision edges (features.collision_mode)")
    from gns.ensemble import check_members
    check_members(model, [contact], "contact network")
    for what, mine, theirs in (("network mesh", model._graph_settings, contact._graph_settings),
                               ("collision mode", model.collision_mode, contact.collision_mode)):
        if mine != theirs:
            raise ValueError(f"contact network differs from the model in its {what}: {theirs} there, {mine} in the model")


def split_acceleration(model: LearnedSimulator, contact: LearnedSimulator, history: torch.Tensor,
                       graph: GraphBatch) -> torch.Tensor:
    """model.predict_acceleration with its contact network: (N, 3, 3) float64 -> (N, 3) float64."""
    # built once here, read by both networks (an empty set tells the model's there is none)
    graph = replace(graph, collision_edges=model.collision_edges(history[:, -1], graph))
    edges = graph.collision_edges
    touching = torch.zeros(graph.num_graphs, dtype=torch.bool, device=history.device)
    touching[graph.node_graph.index_select(0, torch.cat([edges.senders, edges.receivers]))] = True
    if not bool(touching.any()):
        return model._own_acceleration(history, graph)
    acc = torch.empty(history.shape[0], 3, dtype=torch.float64, device=history.device)
    for part, predict in ((touching, contact.predict_acceleration), (~touching, model._own_acceleration)):
        if bool(part.any()):
            sub, nodes = select_graphs(graph, part)
            acc[nodes] = predict(history.index_select(0, nodes), sub)
    return acc
