"""The floor's symmetries: the groups a rollout averages over (`--symmetrize`), and turns about z
(features.canonical_heading)."""
from __future__ import annotations

import torch


def _maps(*rows) -> tuple:
    return tuple(tuple(tuple(float(v) for v in r) for r in m) for m in rows)


_MIRRORS = _maps(((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
                 ((1, 0, 0), (0, -1, 0), (0, 0, 1)), ((-1, 0, 0), (0, -1, 0), (0, 0, 1)))
# the floor's symmetries a rollout may average over (3x3 maps of the world, z kept): "d2" the
# identity, the mirrors in x and in y and the half turn; "d4" also the quarter turns and the
# diagonal mirrors (x and y swapped), at twice the cost; "d1" (the identity and the mirror in x)
# and "c2" (the identity and the half turn) at half the cost, "c4" (the quarter turns) at the same:
# which of d2's gain is the exact mirror and which the average over images (docs/speed.md)
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
