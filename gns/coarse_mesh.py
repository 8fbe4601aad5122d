"""A coarser mesh for the network than for the object (features.mesh_vertices).

The network's cost grows with the vertices and edges of every object graph: MOVi-A's shapes
have 51-64 hull vertices, far more than the motion of a rigid body needs to be told (3 points
fix a pose). With `features.mesh_vertices = n`, the network sees n of each mesh's vertices,
spread over the surface by farthest-point sampling, joined by the edges of their convex hull;
shape matching turns the predicted vertices into a pose, and everything scored or written
(poses, penetration of the full mesh) uses the dataset's own mesh. Training and rollouts build
their graphs from the same coarse meshes, so the model never sees the full one.

The choice is deterministic (a function of the mesh alone): a checkpoint keeps `n`, not the
indices, and rebuilds the same coarse mesh from the meshes it carries.

One n for every shape under-serves round ones: 16 of a sphere's 62 vertices make a hull whose
surface stops up to 13% of its size short of the one PyBullet collides, where a beveled cube's
stops 2% short (docs/speed.md, session 15). With `features.mesh_support_gap = g`, a mesh gets
more than n vertices, the fewest whose hull reaches within g x its size of the full mesh in
every direction (`support_gap`): what each shape needs, not what the roundest one needs.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

MIN_VERTICES = 4  # a solid's hull needs 4 points not in one plane


def farthest_order(vertices: np.ndarray, n: int) -> np.ndarray:
    """Indices of n vertices in the order chosen, each the farthest from those before it.

    Starts at the vertex farthest from the vertex mean; ties go to the lowest index, so the
    choice depends on the mesh only. The first k of n are the choice for k (nested subsets).
    """
    v = np.asarray(vertices, np.float64)
    chosen = [int(np.argmax(np.linalg.norm(v - v.mean(0), axis=1)))]
    dist = np.linalg.norm(v - v[chosen[0]], axis=1)
    for _ in range(min(n, len(v)) - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(v - v[nxt], axis=1))
    return np.asarray(chosen, np.int64)


def farthest_points(vertices: np.ndarray, n: int) -> np.ndarray:
    """Indices of n vertices, each the farthest from those chosen before it (sorted)."""
    return np.sort(farthest_order(vertices, n))


def _directions(count: int = 2000) -> np.ndarray:
    """count unit vectors spread evenly over the sphere (a Fibonacci lattice: fixed, no randomness)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def support_gap(vertices: np.ndarray, subset: np.ndarray) -> float:
    """How far the hull of vertices[subset] stops short of the hull of all vertices, at most over
    2000 directions and the direction of every vertex from the centre, as a fraction of the
    mesh's largest extent (the metrics' object size): with that direction down, how much of the
    object the network's mesh does not reach. The gap peaks at a kink (where the subset's
    nearest vertices tie), often towards a left-out vertex, which a lattice alone misses by its
    spacing (1.7% of a cube's side for its corner)."""
    return _Support(vertices).gap(subset)


class _Support:
    """A mesh's vertices projected on the support directions once, for the gap of any subset."""

    def __init__(self, vertices: np.ndarray):
        v = np.asarray(vertices, np.float64)
        radial = v - v.mean(0)
        radial = radial[np.linalg.norm(radial, axis=1) > 0]
        d = np.concatenate([_directions(), radial / np.linalg.norm(radial, axis=1, keepdims=True)])
        self.projected = v @ d.T
        self.full = self.projected.max(0)
        self.size = np.ptp(v, axis=0).max()

    def gap(self, subset: np.ndarray) -> float:
        return float((self.full - self.projected[subset].max(0)).max() / self.size)


def vertices_for_gap(vertices: np.ndarray, n: int, gap: float) -> int:
    """The fewest vertices, at least n, whose farthest-point hull is within gap (a fraction of
    the size) of the full mesh in every direction; all of them if no fewer do."""
    order = farthest_order(vertices, len(vertices))
    support = _Support(vertices)
    for k in range(n, len(order)):
        if support.gap(order[:k]) <= gap:
            return k
    return len(order)


def coarsen(vertices: np.ndarray, faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) with at most n vertices: the farthest-point subset and its convex
    hull's triangles, wound outward. A mesh with n vertices or fewer comes back unchanged."""
    v = np.asarray(vertices, np.float64)
    if n <= 0 or len(v) <= n:
        return v, np.asarray(faces, np.int64)
    if n < MIN_VERTICES:
        raise ValueError(f"features.mesh_vertices must be 0 (all) or >= {MIN_VERTICES}, got {n}")
    sub = v[farthest_points(v, n)]
    hull = ConvexHull(sub)
    if len(hull.vertices) < len(sub):
        # the hull's points are all vertices of the original hull, so none is inside, unless the
        # mesh was not convex; a vertex left out would have no edge and learn nothing
        raise ValueError(f"{len(sub) - len(hull.vertices)} of the {n} chosen vertices are inside their hull "
                         "(the mesh is not convex): use features.mesh_vertices=0")
    tri = hull.simplices.astype(np.int64)
    a, b, c = sub[tri[:, 0]], sub[tri[:, 1]], sub[tri[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - sub.mean(0)) < 0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    return sub, tri


def network_meshes(meshes: dict, n: int, gap: float = 0.0) -> dict:
    """Every mesh of {name: (vertices, faces)} coarsened to n vertices (0 = unchanged), or with
    gap > 0 to the fewest (at least n) within gap of the full mesh (vertices_for_gap)."""
    if n <= 0:
        return meshes
    return {name: coarsen(v, f, vertices_for_gap(v, n, gap) if gap > 0 else n) for name, (v, f) in meshes.items()}
