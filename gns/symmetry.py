"""The floor's symmetries and the canonical frames a model may be turned into: the groups a
rollout averages over (`--symmetrize`), turns about z, the mirror choice of
features.canonical_mirror and the body frame of features.canonical_body_frame."""
from __future__ import annotations

from dataclasses import replace

import torch

from gns.graph import GraphBatch, with_symmetries


def _maps(*rows) -> tuple:
    return tuple(tuple(tuple(float(v) for v in r) for r in m) for m in rows)


_MIRRORS = _maps(((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
                 ((1, 0, 0), (0, -1, 0), (0, 0, 1)), ((-1, 0, 0), (0, -1, 0), (0, 0, 1)))
# the floor's symmetries a rollout may average over (3x3 maps of the world, z kept): "d2" the
# identity, the mirrors in x and in y and the half turn; "d4" also the quarter turns and the
# diagonal mirrors (x and y swapped), at twice the cost; "d1" (the identity and the mirror in x)
# and "c2" (the identity and the half turn) at half the cost, "c4" (the quarter turns) at the same:
# which of d2's gain is the exact mirror and which the average over images (docs/speed.md, session 12)
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


def z_turns(angle: torch.Tensor) -> torch.Tensor:
    """(N,) angles -> (N, 3, 3) rotations about z by them."""
    c, s = torch.cos(angle), torch.sin(angle)
    turn = torch.zeros(angle.shape[0], 3, 3, dtype=angle.dtype, device=angle.device)
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1], turn[:, 2, 2] = c, -s, s, c, 1.0
    return turn


def turn_about_z(v: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """v (N, ..., 3) turned about z by the angles whose cosines and sines are cos, sin (N,):
    z_turns(angle) @ v without building the (N, 3, 3) matrices (a batched matmul of 3x3s is
    several times slower on CPU)."""
    shape = (-1,) + (1,) * (v.dim() - 2)
    c, s = cos.view(shape), sin.view(shape)
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, v[..., 2]], -1)


def mirror_signs(history: torch.Tensor, scene: torch.Tensor, count: int) -> torch.Tensor:
    """(count,) +-1 per scene: the sign of the x plus z parts of its angular momentum about its
    centre, sum of (x_t - centre) x (x_t - x_{t-1}) over its nodes, which a mirror in y flips
    (+1 where it is 0). history (N, 3 frames, 3)."""
    x, v = history[:, -1], history[:, -1] - history[:, -2]
    nodes = torch.bincount(scene, minlength=count).clamp(min=1).to(x.dtype)
    centre = torch.zeros(count, 3, dtype=x.dtype, device=x.device).index_add_(0, scene, x) / nodes[:, None]
    spin = torch.zeros(count, 3, dtype=x.dtype, device=x.device).index_add_(0, scene, torch.cross(x - centre[scene], v, dim=1))
    return torch.where(spin[:, 0] + spin[:, 2] < 0, -1.0, 1.0).to(x.dtype)


def canonical_body_frame(x: torch.Tensor, graph: GraphBatch, rot: torch.Tensor) -> tuple[GraphBatch, torch.Tensor]:
    """graph with each object's rest shape described in the equivalent body frame (one of its
    symmetries S: r -> S r, pose R -> R S^T) whose pose is closest to the identity (largest trace
    of R S^T; ties to the first), and those poses (G, 3, 3). rot: each object's pose R at
    positions x (N, 3) (shape_match_packed). The world vertices are unchanged, so this only
    relabels what the rest features say; the choice is a discrete one, made without gradient
    (features.canonical_body_frame)."""
    if graph.symmetries is None:
        graph = with_symmetries(graph)
    syms, counts = graph.symmetries, graph.num_symmetries
    with torch.no_grad():
        score = torch.einsum("gij,gkij->gk", rot.detach(), syms.to(rot.dtype))
        padding = torch.arange(syms.shape[1], device=score.device)[None] >= counts.to(score.device)[:, None]
        pick = score.masked_fill(padding, -torch.inf).argmax(1)
    s = syms[torch.arange(graph.num_graphs, device=pick.device), pick].to(graph.rest.dtype)   # (G, 3, 3)
    # S G S^T = G: the groups stay as they are
    graph = replace(graph, rest=torch.einsum("nij,nj->ni", s[graph.node_graph], graph.rest),
                    full_rest=mapped_full_rest(graph, lambda full: full @ s.transpose(1, 2).to(full.dtype)))
    return graph, rot @ s.transpose(1, 2).to(rot.dtype)


def mapped_full_rest(graph: GraphBatch, map_full) -> torch.Tensor | None:
    """graph.full_rest mapped as its rest was (a mirror, a body-frame symmetry), if it has one."""
    return None if graph.full_rest is None else map_full(graph.full_rest)
