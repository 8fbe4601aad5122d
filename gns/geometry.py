"""Rigid-body geometry in numpy: quaternions (w, x, y, z), rotation matrices, posed vertices.

Everything is vectorised over leading axes ("...") so one call handles a whole trajectory
(T, N, ...) at once. Quaternions follow the dataset's convention: w x y z, body -> world, so
world = R(q) @ body. Numpy only: the metrics, plots and data importers use this module without
torch. quat_to_matrix and matrix_to_quat are written out rather than scipy's: training inputs
are built with quat_to_matrix (scipy rounds differently in the last bit, so runs would no longer
repeat bit for bit), matrix_to_quat passes the NaN of a diverged rollout through where scipy
raises, and both mirror their torch twins in gns.api.
"""
from __future__ import annotations

import numpy as np

from datagen.quaternions import rotation


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 4) unit quaternions. A zero quaternion raises, not NaNs."""
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise ValueError("cannot normalise a zero quaternion")
    return q / n


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 4): the inverse rotation of a unit quaternion."""
    q = np.asarray(q, np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (..., 4) quaternions (broadcasting): rotate by b, then by a."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_from_axis_angle(axis, angle) -> np.ndarray:
    """Axis (..., 3) (need not be unit) and angle (...) in radians -> (..., 4) wxyz."""
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * np.asarray(angle, np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> (..., 3, 3) rotation matrices. q is normalised first, so a slightly
    non-unit quaternion (float32 round-off, measured data) still gives a proper rotation."""
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    r = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return r.reshape(r.shape[:-1] + (3, 3))


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit wxyz quaternions with w >= 0.

    Shepperd's method: for each matrix, pick the largest of 4w^2, 4x^2, 4y^2, 4z^2 (read off
    the trace and diagonal) and divide by it, so no branch ever divides by a small number.
    """
    m = np.asarray(m, np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate solutions, one per largest component, all computed then selected per item.
    cands = np.stack([
        np.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2],
                  m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22,
                  m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                  1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
        np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                  m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], axis=-2)  # (..., 4 candidates, 4 components)
    diag = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                     1 - m00 - m11 + m22], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in radians, in [0, pi], of the rotation a * conj(b) (taking b to a); (..., 4) -> (...).

    Mathematically 2 arccos(|<a, b>|) (q and -q are the same rotation). scipy's magnitude is
    2 atan2(|vector part|, |w|) of the relative quaternion instead, because arccos loses half
    the digits near 1: identical rotations would score ~1e-8 degrees instead of 0.
    """
    return (rotation(quat_normalize(a)) * rotation(quat_normalize(b)).inv()).magnitude()


def pose_to_vertices(positions: np.ndarray, quaternions: np.ndarray, scale, rest_vertices: np.ndarray) -> np.ndarray:
    """World vertices R(q) @ (scale * rest) + position.

    positions (..., 3), quaternions (..., 4) wxyz, scale scalar or (...) broadcastable with the
    leading axes, rest_vertices (V, 3) of the unit asset -> (..., V, 3).
    """
    positions = np.asarray(positions, np.float64)
    rot = quat_to_matrix(quaternions)                                  # (..., 3, 3)
    scale = np.asarray(scale, np.float64)[..., None, None]             # (..., 1, 1)
    body = scale * np.asarray(rest_vertices, np.float64)               # (..., V, 3)
    return np.einsum("...ij,...vj->...vi", rot, body) + positions[..., None, :]


def feature_edges(faces: np.ndarray, vertices: np.ndarray, angle_deg: float = 1.0) -> np.ndarray:
    """(E, 2) vertex pairs of a triangle mesh's edges, dropping edges between coplanar triangles.

    The triangulation diagonals of a flat face are not edges of the solid; drawing them clutters
    plots of a cube. Boundary edges (one triangle) are kept.
    """
    faces = np.asarray(faces, np.int64)
    v = np.asarray(vertices, np.float64)
    normals = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    edges = np.sort(edges, axis=1)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    uniq, start, counts = np.unique(edges, axis=0, return_index=True, return_counts=True)
    keep = np.ones(len(uniq), bool)
    two = counts == 2
    cos = np.sum(normals[owner[start[two]]] * normals[owner[start[two] + 1]], axis=1)
    keep[two] = cos < np.cos(np.radians(angle_deg))
    return uniq[keep]
