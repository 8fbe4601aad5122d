"""gns.geometry: quaternions, rotation matrices and posed vertices."""

import numpy as np

from datagen.scenes import get_shape
from gns.geometry import (matrix_to_quat, pose_to_vertices, quat_conjugate, quat_from_axis_angle,
                          quat_multiply, quat_normalize, quat_to_matrix, rotation_angle)

CUBE = get_shape("cube")
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def random_quats(n, seed=0):
    return quat_normalize(np.random.default_rng(seed).normal(size=(n, 4)))


def test_quaternion_matrix_round_trip():
    q = random_quats(500)
    R = quat_to_matrix(q)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    q2 = matrix_to_quat(R)
    assert np.all(q2[:, 0] >= 0)
    assert np.allclose(np.abs(np.sum(q * q2, axis=1)), 1.0)  # same rotation up to sign
    assert np.allclose(quat_to_matrix(q2), R, atol=1e-12)


def test_matrix_to_quat_half_turns_and_identity():
    # w = 0 for half turns: the branch that divides by w would fail here.
    for axis in np.eye(3).tolist() + [[1, 1, 0], [1, -2, 3]]:
        q = quat_from_axis_angle(axis, np.pi)
        assert np.allclose(quat_to_matrix(matrix_to_quat(quat_to_matrix(q))), quat_to_matrix(q), atol=1e-12)
    assert np.allclose(matrix_to_quat(np.eye(3)), IDENTITY)


def test_quaternion_convention_wxyz_body_to_world():
    q = quat_from_axis_angle([0, 0, 1], np.pi / 2)  # 90 degrees about z
    assert np.allclose(q, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(quat_to_matrix(q) @ [1, 0, 0], [0, 1, 0])  # x axis of the body -> world y


def test_quat_multiply_matches_matrix_product_and_conjugate_inverts():
    a, b = random_quats(50, 1), random_quats(50, 2)
    assert np.allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b))
    assert np.allclose(np.abs(quat_multiply(a, quat_conjugate(a))), IDENTITY, atol=1e-12)


def test_rotation_angle_equals_arccos_form_and_is_exact_at_zero():
    a, b = random_quats(300, 3), random_quats(300, 4)
    ref = 2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0, 1))
    assert np.allclose(rotation_angle(a, b), ref, atol=1e-9)
    assert np.all(rotation_angle(a, a) < 1e-12)


def test_pose_to_vertices_cube_corners():
    q = quat_from_axis_angle([0, 0, 1], np.pi / 4)
    v = pose_to_vertices(np.array([1.0, 2.0, 3.0]), q, 2.0, CUBE.vertices)
    assert v.shape == (8, 3)
    assert np.allclose(np.sort(np.unique(v[:, 2].round(9))), [2.0, 4.0])
    assert np.allclose(np.abs(v[:, :2] - [1, 2]).max(axis=0), np.sqrt(2))  # corners on the diagonals
    # vectorised over (T, N)
    vv = pose_to_vertices(np.zeros((5, 2, 3)), np.broadcast_to(IDENTITY, (5, 2, 4)), np.ones(2), CUBE.vertices)
    assert vv.shape == (5, 2, 8, 3)


