"""Rigid-body geometry: quaternions (w, x, y, z), rotation matrices and posed vertices in numpy,
and the rigid steps of a rollout in torch (the integrator, posing, shape matching; further down).

Everything is vectorised over leading axes ("...") so one call handles a whole trajectory
(T, N, ...) at once. Quaternions follow the dataset's convention: w x y z, body -> world, so
world = R(q) @ body. The numpy half is what the metrics, plots and data importers use. quat_to_matrix and matrix_to_quat are written out rather than scipy's: training inputs
are built with quat_to_matrix (scipy rounds differently in the last bit, so runs would no longer
repeat bit for bit), matrix_to_quat passes the NaN of a diverged rollout through where scipy
raises, and both mirror their torch twins in gns.api.
"""
from __future__ import annotations

import numpy as np
import torch

from datagen.shards import rotation


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


# Rigid-body steps in torch, batched over the objects of a packed graph (float64 positions):
# the integrator and its exact inverse, posing rest shapes, and shape
# matching (the best rigid fit of a rest shape to predicted vertices, with a finite gradient for
# the training's rigid loss).


def integrate(x_tm1: torch.Tensor, x_t: torch.Tensor, acceleration: torch.Tensor) -> torch.Tensor:
    """Semi-implicit Euler with dt = one frame: x_{t+1} = x_t + (x_t - x_{t-1}) + a. (N, 3) each."""
    return x_t + (x_t - x_tm1) + acceleration


def acceleration_of(x_tm1: torch.Tensor, x_t: torch.Tensor, x_tp1: torch.Tensor) -> torch.Tensor:
    """The inverse of `integrate`: a = x_{t+1} - 2 x_t + x_{t-1}. (N, 3) each."""
    return (x_tp1 - x_t) - (x_t - x_tm1)


def posed(rot: torch.Tensor, t: torch.Tensor, node_graph: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """The rest vertices (N, 3) of each graph placed at its pose, rotation rot (G, 3, 3) and
    translation t (G, 3): R rest + t per node."""
    return rotate_nodes(rot, node_graph, rest) + t.index_select(0, node_graph)


def posed_heights(rot: torch.Tensor, t: torch.Tensor, node_graph: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """posed(...)[:, 2] (N,) alone, to the last bit (the same products summed in the same order), at
    a third of the cost: where only heights are read (how near the floor a pose takes an object)."""
    r = rot[:, 2].index_select(0, node_graph)
    return r[:, 0] * rest[:, 0] + r[:, 1] * rest[:, 1] + r[:, 2] * rest[:, 2] + t[:, 2].index_select(0, node_graph)


def rotate_nodes(rot: torch.Tensor, node_graph: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """v (N, 3) turned by its graph's rotation rot (G, 3, 3): rot[node_graph] @ v per node. As
    three column products after index_select: on CPU, rot[node_graph] and a batched (N, 3, 3) x
    (N, 3, 1) matmul cost ~4x as much, ~10% of a rollout step of a small model (experiments/log.md)."""
    r = rot.index_select(0, node_graph)
    return r[:, :, 0] * v[:, :1] + r[:, :, 1] * v[:, 1:2] + r[:, :, 2] * v[:, 2:]


def _rotation_from_covariance(h: torch.Tensor) -> torch.Tensor:
    """Rotation part of the polar decomposition of h (B, 3, 3), never a reflection.

    For h = sum_i p_i q_i^T = U S V^T, R = U diag(1, 1, det(U V^T)) V^T maximises
    sum_i p_i . R q_i over proper rotations (Kabsch). A non-finite h (a diverged prediction)
    gives a NaN rotation for its graph only, instead of stopping LAPACK for the whole batch.
    """
    finite = torch.isfinite(h).all(dim=(1, 2))
    eye = torch.eye(3, dtype=h.dtype, device=h.device)
    u, _, vh = torch.linalg.svd(torch.where(finite[:, None, None], h, eye))
    sign = torch.linalg.det(u @ vh)
    fix = torch.ones_like(h[:, 0])
    fix[:, 2] = sign
    rot = (u * fix[:, None, :]) @ vh
    return torch.where(finite[:, None, None], rot, torch.nan)


POLAR_ITERATIONS = 12


def _rotation_differentiable(h: torch.Tensor) -> torch.Tensor:
    """`_rotation_from_covariance` with a finite gradient: the polar factor by scaled Newton
    iteration X <- (g X + X^-T / g) / 2 (Higham), which converges quadratically and to double
    precision within POLAR_ITERATIONS for any well-conditioned h. The SVD's gradient divides by
    differences of singular values, and a cube's isotropic rest shape makes them all equal, so
    it is infinite exactly where rigid objects need it. A covariance whose polar factor is a
    reflection (det h < 0, a prediction turned inside out) takes the SVD's rotation, without
    gradient."""
    finite = torch.isfinite(h).all(dim=(1, 2))
    eye = torch.eye(3, dtype=h.dtype, device=h.device)
    x = torch.where(finite[:, None, None], h, eye)
    x = x / x.norm(dim=(1, 2), keepdim=True)
    for _ in range(POLAR_ITERATIONS):
        inv_t = torch.linalg.inv(x).transpose(1, 2)
        g = (inv_t.norm(dim=(1, 2), keepdim=True) / x.norm(dim=(1, 2), keepdim=True)).sqrt()
        x = 0.5 * (g * x + inv_t / g)
    proper = (torch.linalg.det(x) > 0)[:, None, None]
    rot = torch.where(proper, x, _rotation_from_covariance(h.detach()))
    return torch.where(finite[:, None, None], rot, torch.nan)


def _rotation(h: torch.Tensor) -> torch.Tensor:
    if torch.is_grad_enabled() and h.requires_grad:
        return _rotation_differentiable(h)
    return _rotation_from_covariance(h)


def shape_match(x: torch.Tensor, rest: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best rigid transform of the rest shape onto the points, batched.

    x: (B, V, 3) predicted vertices; rest: (B, V, 3) rest vertices in the body frame.
    Returns R (B, 3, 3), t (B, 3) with x ~ R rest + t (t is the pose translation, so it is the
    centre of mass when rest is centred on it), and x_proj = R rest + t (B, V, 3).
    """
    cx, cr = x.mean(1, keepdim=True), rest.mean(1, keepdim=True)
    h = (x - cx).transpose(1, 2) @ (rest - cr)
    rot = _rotation(h)
    t = cx[:, 0] - (rot @ cr[:, 0, :, None])[..., 0]
    return rot, t, rest @ rot.transpose(1, 2) + t[:, None]


def _packed_fit(a: torch.Tensor, b: torch.Tensor, node_graph: torch.Tensor, num_graphs: int):
    """Per graph of a packed batch: the point sets' means ca, cb (G, 3), a's offsets p = a - ca
    (N, 3) and the covariance h = sum p (b - cb)^T (G, 3, 3), whose polar factor best turns b's
    offsets onto a's (Kabsch)."""
    count = torch.zeros(num_graphs, dtype=a.dtype, device=a.device).index_add_(
        0, node_graph, torch.ones_like(a[:, 0]))[:, None]
    ca = torch.zeros(num_graphs, 3, dtype=a.dtype, device=a.device).index_add_(0, node_graph, a) / count
    cb = torch.zeros(num_graphs, 3, dtype=a.dtype, device=a.device).index_add_(0, node_graph, b) / count
    p, q = a - ca.index_select(0, node_graph), b - cb.index_select(0, node_graph)
    h = torch.zeros(num_graphs, 3, 3, dtype=a.dtype, device=a.device).index_add_(
        0, node_graph, p[:, :, None] * q[:, None, :])
    return ca, cb, p, h


def fit_packed(x: torch.Tensor, rest: torch.Tensor, node_graph: torch.Tensor,
               num_graphs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """`shape_match_packed`'s pose alone, R (G, 3, 3) and t (G, 3): for a caller that places
    other vertices than those fitted, or none."""
    cx, cr, _, h = _packed_fit(x, rest, node_graph, num_graphs)
    rot = _rotation(h)
    return rot, cx - (rot @ cr[:, :, None])[..., 0]


def placed_around(part: torch.Tensor, seen: tuple, graph) -> torch.Tensor:
    """Every vertex of `graph` (a GraphBatch) at the pose shape matching fits to `part`, the
    positions of the nodes `seen` = (their graph, their indices), which keep their own: where a
    network moved some nodes of each object (LearnedSimulator.network_nodes)."""
    sub, nodes = seen
    rot, t = fit_packed(part, sub.rest, sub.node_graph, sub.num_graphs)
    return posed(rot, t, graph.node_graph, graph.rest).index_put((nodes,), part)


def shape_match_packed(x: torch.Tensor, rest: torch.Tensor, node_graph: torch.Tensor,
                       num_graphs: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`shape_match` for a packed batch with different vertex counts per graph.

    x, rest: (N, 3); node_graph: (N,) graph index. Returns R (G, 3, 3), t (G, 3), x_proj (N, 3).
    """
    rot, t = fit_packed(x, rest, node_graph, num_graphs)
    return rot, t, posed(rot, t, node_graph, rest)
