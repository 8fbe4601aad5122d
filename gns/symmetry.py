"""The symmetries a rollout may average a model's predictions over, each a rollout option: the
floor's (`--symmetrize`: mirrors and turns about z that leave the floor and gravity as they are)
and each object's body frames (`--body-frames`: the rotations mapping its mesh onto itself, which
gns.graph.mesh_symmetries finds), with the turns about z of features.canonical_heading.

A network trained with random turns about z is only approximately equivariant to them; the
average over a scene's images is exactly so, at one network call an image. Loaded only when a
model or a rollout asks for one of them.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from gns.graph import EdgeSet, GraphBatch, mesh_symmetries, padded_groups


def mapped_symmetries(graph: GraphBatch, g: torch.Tensor) -> torch.Tensor | None:
    """The symmetry groups of graph's rest shapes once rest is mapped r -> g r (g (3, 3) for all
    graphs or (G, 3, 3) per graph, orthogonal): g S g^T. None if graph carries none."""
    if graph.symmetries is None:
        return None
    g = g.to(graph.symmetries)
    if g.dim() == 2 and bool((g == torch.diag(torch.diagonal(g))).all()):
        # the floor's mirrors and half turn (symmetrized rollouts, every step): g S g^T is S
        # with entry (i, j) times g_ii g_jj, without two batched matmuls
        d = torch.diagonal(g)
        return graph.symmetries * (d[:, None] * d[None, :])
    g = g[:, None] if g.dim() == 3 else g
    return g @ graph.symmetries @ g.transpose(-1, -2)


def with_symmetries(graph: GraphBatch) -> GraphBatch:
    """A copy of graph carrying each graph's body-frame symmetry group (mesh_symmetries of its
    rest shape), for predictions averaged over them (LearnedSimulator.body_frames)."""
    rest = graph.rest.detach().cpu().numpy()
    owner = graph.node_graph.cpu().numpy()
    padded, counts = padded_groups([mesh_symmetries(rest[owner == g]) for g in range(graph.num_graphs)])
    return replace(graph, symmetries=padded.to(graph.rest), num_symmetries=counts.to(graph.rest.device))


def stack_graphs(graphs: list[GraphBatch]) -> GraphBatch:
    """One batch holding the given batches one after the other (nodes, edges, faces renumbered);
    each keeps its scenes to itself (scene numbers offset), so no collision edge joins two of
    them. Collision edges are kept only if every batch has them (else rebuilt by the caller)."""
    first = graphs[0]
    node_offset = torch.cumsum(torch.tensor([0] + [g.num_nodes for g in graphs[:-1]]), 0).tolist()
    graph_offset = torch.cumsum(torch.tensor([0] + [g.num_graphs for g in graphs[:-1]]), 0).tolist()

    def edges(sets: list[EdgeSet | None]) -> EdgeSet | None:
        if any(e is None for e in sets):
            return None
        extra = [None if sets[0].vectors is None else torch.cat([e.vectors for e in sets]),
                 None if sets[0].signed is None else torch.cat([e.signed for e in sets])]
        return EdgeSet(torch.cat([e.senders + o for e, o in zip(sets, node_offset)]),
                       torch.cat([e.receivers + o for e, o in zip(sets, node_offset)]), *extra)

    scenes = None
    if first.graph_scene is not None:
        # scene numbers of each batch moved past the previous batch's largest
        parts, base = [], 0
        for g in graphs:
            parts.append(g.graph_scene + base)
            base += int(g.graph_scene.max()) + 1 if g.num_graphs else 0
        scenes = torch.cat(parts)
    cat = lambda name: None if getattr(first, name) is None else torch.cat([getattr(g, name) for g in graphs])  # noqa: E731
    return GraphBatch(
        mesh_edges=edges([g.mesh_edges for g in graphs]), rest=cat("rest"), material=cat("material"),
        node_graph=torch.cat([g.node_graph + o for g, o in zip(graphs, graph_offset)]),
        num_graphs=sum(g.num_graphs for g in graphs), graph_scene=scenes,
        collision_edges=edges([g.collision_edges for g in graphs]),
        faces=None if first.faces is None else torch.cat([g.faces + o for g, o in zip(graphs, node_offset)]),
        symmetries=cat("symmetries"), num_symmetries=cat("num_symmetries"))


IMAGE_NODES = 32768  # most nodes in one network call of symmetrized images (averaged_over_images)


def _maps(*rows) -> tuple:
    return tuple(tuple(tuple(float(v) for v in r) for r in m) for m in rows)


_MIRRORS = _maps(((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
                 ((1, 0, 0), (0, -1, 0), (0, 0, 1)), ((-1, 0, 0), (0, -1, 0), (0, 0, 1)))
# the floor's symmetries a rollout may average over (3x3 maps of the world, z kept): "d2" the
# identity, the mirrors in x and in y and the half turn; "d4" also the quarter turns and the
# diagonal mirrors (x and y swapped), at twice the cost; "d1" (the identity and the mirror in x)
# and "c2" (the identity and the half turn) at half the cost, "c4" (the quarter turns) at the same:
# which of d2's gain is the exact mirror and which the average over images (experiments/log.md)
SYMMETRY_GROUPS = {"d2": _MIRRORS,
                   "d4": _MIRRORS + tuple(tuple((m[1], m[0], m[2])) for m in _MIRRORS),
                   "d1": (_MIRRORS[0], _MIRRORS[1]),
                   "c2": (_MIRRORS[0], _MIRRORS[3]),
                   "c4": (_MIRRORS[0], _maps(((0, -1, 0), (1, 0, 0), (0, 0, 1)))[0], _MIRRORS[3],
                          _maps(((0, 1, 0), (-1, 0, 0), (0, 0, 1)))[0])}
FLOOR_SYMMETRIES = SYMMETRY_GROUPS["d2"]


def symmetry_group(symmetrize) -> str | None:
    """The group a `symmetrize` setting names: False/None -> None, True -> "d2", or a key of
    SYMMETRY_GROUPS."""
    if symmetrize is None or symmetrize is False:
        return None
    if symmetrize is True:
        return "d2"
    if symmetrize not in SYMMETRY_GROUPS:
        raise ValueError(f"unknown symmetry group {symmetrize!r}; known: {', '.join(SYMMETRY_GROUPS)}")
    return symmetrize


def turn_about_z(v: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """v (N, ..., 3) turned about z by the angles whose cosines and sines are cos, sin (N,):
    the rotation matrices' product with v without building the (N, 3, 3) matrices (a batched matmul of 3x3s is
    several times slower on CPU)."""
    shape = (-1,) + (1,) * (v.dim() - 2)
    c, s = cos.view(shape), sin.view(shape)
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, v[..., 2]], -1)


def _mapped_edges(edges, g: torch.Tensor):
    """A graph's collision edges in the image under the orthogonal map g: the same pairs (distances
    are kept), their vectors mapped, their signed distances kept; None stays None (built there)."""
    if edges is None or edges.vectors is None:
        return edges
    v = edges.vectors.view(len(edges.vectors), -1, 3)   # face edges carry two vectors
    return replace(edges, vectors=(v @ g.T.to(v.dtype)).reshape(edges.vectors.shape))


def averaged_over_images(model, history: torch.Tensor, graph: GraphBatch, symmetrize, body_frames: bool) -> torch.Tensor:
    """A model's acceleration (N, 3) float64 for history (N, 3, 3), averaged over images of the
    scene (`model`: a gns.simulator.LearnedSimulator, called for the normalised acceleration).

    With `symmetrize` (a group of SYMMETRY_GROUPS, a rollout option, off by default), over the
    world's floor symmetries, e.g. d2's {identity, mirror x, mirror y, half turn about z}: each maps
    the input, the network predicts, the map is undone. The result is exactly equivariant
    to those maps applied to the scene, body frames included (a cube tilted 45 + d is the mirror
    of one tilted 45 - d only up to its body frame: docs/results.md), where
    the network alone is only approximately so (trained with random z rotations).
    With `body_frames` too, each object's rest shape is also described in every one of
    its equivalent body frames (graph.symmetries, the rotations mapping its mesh onto itself,
    e.g. a cube's 24) and the predictions averaged: exactly invariant to which frame describes
    an object, at that many times the cost."""
    syms = graph.symmetries if body_frames else None
    if not symmetrize and syms is None:
        return model.target_normalizer.inverse(model(history, graph).to(torch.float64))
    group = symmetry_group(symmetrize)
    floors = SYMMETRY_GROUPS[group] if group else FLOOR_SYMMETRIES[:1]
    frames = 1 if syms is None else syms.shape[1]
    inputs, graphs, maps = [], [], []
    for k in range(frames):
        if syms is None:
            rest, weight = graph.rest, 1.0
        else:
            # the same world vertices described in the k-th equivalent body frame (r -> S r):
            # the answer may not hang on which one, so average over all of each object's group
            rest = torch.einsum("nij,nj->ni", syms[graph.node_graph, k], graph.rest)
            counts = graph.num_symmetries[graph.node_graph]
            weight = ((k < counts).to(history.dtype) / counts.to(history.dtype))[:, None]
        for m in floors:
            g = torch.tensor(m, dtype=history.dtype, device=history.device)
            # the body frame is mapped too (x = R rest + p -> (g R g^T) (g rest) + g p): the
            # network sees a proper rotation, as in training, and the average is exactly equivariant
            inputs.append(history @ g.T)
            graphs.append(replace(graph, rest=rest @ g.T, collision_edges=_mapped_edges(graph.collision_edges, g),
                                  symmetries=mapped_symmetries(graph, g)))
            maps.append((g, weight))
    # images share network calls: per node, a call on 6400 nodes costs ~0.6x one on 1600;
    # calls stay under IMAGE_NODES nodes (24 body frames x 4 mirrors of a batch would not fit)
    per_call = max(1, IMAGE_NODES // max(graph.num_nodes, 1))
    total = torch.zeros_like(history[:, -1])
    for lo in range(0, len(maps), per_call):
        hi = min(lo + per_call, len(maps))
        out = model.target_normalizer.inverse(
            model(torch.cat(inputs[lo:hi]), stack_graphs(graphs[lo:hi])).to(torch.float64))
        for a, (g, weight) in zip(out.split(graph.num_nodes), maps[lo:hi]):
            total = total + (a @ g) * weight   # g^T a: the map undone
    return total / len(floors)
