"""The floor's symmetries: the groups a rollout averages over (`--symmetrize`) and the average of
a model's predictions over their images, and turns about z (features.canonical_heading)."""
from __future__ import annotations

from dataclasses import replace

import torch

from gns.graph import GraphBatch, mapped_symmetries, stack_graphs

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
            graphs.append(replace(graph, rest=rest @ g.T, collision_edges=None,
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
