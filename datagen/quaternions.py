"""Quaternions in the dataset's order (w x y z, body -> world) and scipy's Rotation, which holds
them x y z w: the conversions, and the sign choice that keeps a trajectory on one cover."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def wxyz(q_xyzw) -> np.ndarray:
    """(..., 4) x y z w (scipy, PyBullet) -> w x y z."""
    return np.asarray(q_xyzw)[..., [3, 0, 1, 2]]


def xyzw(q_wxyz) -> np.ndarray:
    """(..., 4) w x y z -> x y z w (scipy, PyBullet)."""
    return np.asarray(q_wxyz)[..., [1, 2, 3, 0]]


def rotation(q_wxyz) -> Rotation:
    """scipy Rotation(s) of w x y z quaternions (..., 4)."""
    return Rotation.from_quat(xyzw(q_wxyz))


def continuous(quat: np.ndarray) -> np.ndarray:
    """A copy of quaternions (T, ..., 4) with signs flipped so consecutive frames lie on the same
    cover: q and -q are one rotation, and finite differences or interpolation of quaternions
    must not see the jump between them."""
    flips = np.where(np.sum(quat[1:] * quat[:-1], axis=-1) < 0, -1.0, 1.0)
    quat = quat.copy()
    quat[1:] *= np.cumprod(flips, axis=0)[..., None]
    return quat
