"""Rigid-body steps in torch, batched over the objects of a packed graph (float64 positions):
the integrator and its exact inverse, posing rest shapes, and shape
matching (the best rigid fit of a rest shape to predicted vertices, with a finite gradient for
the training's rigid loss). The numpy quaternion and pose helpers of the metrics and plots are
gns.geometry."""
from __future__ import annotations

import torch


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


def shape_match_packed(x: torch.Tensor, rest: torch.Tensor, node_graph: torch.Tensor,
                       num_graphs: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`shape_match` for a packed batch with different vertex counts per graph.

    x, rest: (N, 3); node_graph: (N,) graph index. Returns R (G, 3, 3), t (G, 3), x_proj (N, 3).
    """
    cx, cr, _, h = _packed_fit(x, rest, node_graph, num_graphs)
    rot = _rotation(h)
    t = cx - (rot @ cr[:, :, None])[..., 0]
    x_proj = posed(rot, t, node_graph, rest)
    return rot, t, x_proj
