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
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

MIN_VERTICES = 4  # a solid's hull needs 4 points not in one plane


def farthest_points(vertices: np.ndarray, n: int) -> np.ndarray:
    """Indices of n vertices, each the farthest from those chosen before it (sorted).

    Starts at the vertex farthest from the vertex mean; ties go to the lowest index, so the
    choice depends on the mesh only.
    """
    v = np.asarray(vertices, np.float64)
    chosen = [int(np.argmax(np.linalg.norm(v - v.mean(0), axis=1)))]
    dist = np.linalg.norm(v - v[chosen[0]], axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(v - v[nxt], axis=1))
    return np.sort(np.asarray(chosen, np.int64))


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


def network_meshes(meshes: dict, n: int) -> dict:
    """Every mesh of {name: (vertices, faces)} coarsened to n vertices (0 = unchanged)."""
    if n <= 0:
        return meshes
    return {name: coarsen(v, f, n) for name, (v, f) in meshes.items()}
