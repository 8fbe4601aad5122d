"""gns.metrics on hand-made trajectories with known errors."""
import json

import numpy as np
import pytest

from datagen.scenes import get_shape
from datagen.shards import Scene
from gns.geometry import quat_from_axis_angle, quat_normalize
from gns.metrics import (evaluate_scenes, format_table, penetration_pct, per_frame_curves, per_frame_errors,
                         position_error_pct, rotation_error_deg)

CUBE = get_shape("cube")
MESHES = {"cube": (CUBE.vertices, CUBE.faces)}
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def make_scene(positions, quaternions=None, scale=1.0, shape="cube", material="metal"):
    """A Scene of N objects from (T, N, 3) positions and (T, N, 4) quaternions (identity default)."""
    positions = np.asarray(positions, float)
    T, N = positions.shape[:2]
    if quaternions is None:
        quaternions = np.broadcast_to(IDENTITY, (T, N, 4)).copy()
    z = np.zeros((T, N, 3))
    return Scene(positions=positions, quaternions=np.asarray(quaternions, float), velocities=z,
                 angular_velocities=z, shape=[shape] * N, material=[material] * N,
                 scale=np.full(N, float(scale)), mass=np.ones(N), friction=np.full(N, 0.5),
                 restitution=np.full(N, 0.5))


def resting(T, N=1, z=5.0):
    return np.tile([0.0, 0.0, z], (T, N, 1))


def random_quats(n, seed=0):
    return quat_normalize(np.random.default_rng(seed).normal(size=(n, 4)))


def test_constant_offset_is_percent_of_width():
    true = make_scene(resting(10), scale=0.5)
    pred = make_scene(resting(10) + [0.1, 0, 0], scale=0.5)
    f = per_frame_errors(pred, true, MESHES)
    assert f["position_error_pct"].shape == (10, 1)
    assert np.allclose(f["position_error_pct"], 20.0)
    assert np.allclose(position_error_pct([0.1, 0, 0], [0, 0, 0], 0.5), 20.0)
    r = evaluate_scenes([pred], [true], MESHES)
    assert r["position_error_pct"] == pytest.approx(20.0)
    assert r["rotation_error_deg"] == pytest.approx(0.0)


def test_known_rotation_about_z():
    q = np.broadcast_to(quat_from_axis_angle([0, 0, 1], np.radians(30)), (6, 1, 4))
    r = evaluate_scenes([make_scene(resting(6), q)], [make_scene(resting(6))], MESHES)
    assert r["rotation_error_deg"] == pytest.approx(30.0)
    assert r["position_error_pct"] == pytest.approx(0.0)


def test_double_cover_gives_zero():
    q = random_quats(7, 5)[:, None]
    assert np.allclose(rotation_error_deg(q, -q), 0.0, atol=1e-9)
    r = evaluate_scenes([make_scene(resting(7), -q)], [make_scene(resting(7), q)], MESHES)
    assert r["rotation_error_deg"] == pytest.approx(0.0, abs=1e-9)


def test_sink_below_floor():
    true = make_scene(resting(4, z=0.5))             # resting exactly on the floor: 0
    pred = make_scene(resting(4, z=0.45))            # lowest vertex at -0.05 -> 5% of width 1
    r = evaluate_scenes([pred], [true], MESHES)
    assert r["penetration_pct"] == pytest.approx(5.0)
    assert r["true_penetration_pct"] == pytest.approx(0.0)
    # Turning about z does not change the lowest vertex; above the floor counts as 0.
    qz = quat_from_axis_angle([0, 0, 1], 0.7)
    assert penetration_pct([0, 0, 0.45], qz, 1.0, CUBE.vertices) == pytest.approx(5.0)
    assert penetration_pct([0, 0, 3.0], qz, 1.0, CUBE.vertices) == 0.0
    # A cube on its edge reaches sqrt(2)/2 down; a floor at z = 1 moves the reference.
    qx = quat_from_axis_angle([1, 0, 0], np.pi / 4)
    assert penetration_pct([0, 0, 0.7], qx, 1.0, CUBE.vertices) == pytest.approx(100 * (np.sqrt(0.5) - 0.7))
    assert penetration_pct([0, 0, 1.45], IDENTITY, 1.0, CUBE.vertices, floor_z=1.0) == pytest.approx(5.0)


def test_average_over_frames_then_scenes():
    # Scene A: 4 frames at 10%. Scene B: 10 frames, 0% for 5 then 40% for 5 -> mean 20%.
    # Mean of per-trajectory means = 15; pooling all 14 frames would give 240/14 = 17.1.
    a_true = make_scene(resting(4), scale=1.0)
    a_pred = make_scene(resting(4) + [0.1, 0, 0], scale=1.0)
    b_true = make_scene(resting(10), scale=1.0)
    off = np.zeros((10, 1, 3))
    off[5:, 0, 0] = 0.4
    b_pred = make_scene(resting(10) + off, scale=1.0)
    r = evaluate_scenes([a_pred, b_pred], [a_true, b_true], MESHES)
    assert r["position_error_pct"] == pytest.approx(15.0)
    assert r["num_scenes"] == 2 and r["num_objects"] == 2
    # start=3 scores frames 3.. only: A -> 10, B -> (2*0 + 5*40) / 7.
    r3 = evaluate_scenes([a_pred, b_pred], [a_true, b_true], MESHES, start=3)
    assert r3["position_error_pct"] == pytest.approx((10 + 200 / 7) / 2)
    with pytest.raises(ValueError, match="start"):
        evaluate_scenes([a_pred], [a_true], MESHES, start=4)


def test_horizons_count_from_the_last_given_frame_and_skip_long_ones():
    T = 8
    off = np.zeros((T, 1, 3))
    off[:, 0, 0] = np.arange(T) / 100.0              # error at frame t = t % of width 1
    r = evaluate_scenes([make_scene(resting(T) + off)], [make_scene(resting(T))], MESHES, horizons=(1, 5, 6, 20))
    assert set(r["horizons"]) == {"1", "5"}          # frame 2+6 = 8 is past the end
    assert r["horizons"]["1"]["position_error_pct"] == pytest.approx(3.0)
    assert r["horizons"]["5"]["position_error_pct"] == pytest.approx(7.0)
    assert r["horizons"]["5"]["num_objects"] == 1


def test_breakdowns_by_shape_size_material_and_json():
    sphere = get_shape("sphere")
    meshes = {**MESHES, "sphere": (sphere.vertices, sphere.faces)}
    s1 = make_scene(resting(5), scale=0.7, material="metal")
    p1 = make_scene(resting(5) + [0.07, 0, 0], scale=0.7, material="metal")        # 10%
    s2 = make_scene(resting(5), scale=1.4, shape="sphere", material="rubber")
    p2 = make_scene(resting(5) + [0, 0.42, 0], scale=1.4, shape="sphere", material="rubber")  # 30%
    r = evaluate_scenes([p1, p2], [s1, s2], meshes)
    assert r["position_error_pct"] == pytest.approx(20.0)
    assert r["by_shape"]["cube"]["position_error_pct"] == pytest.approx(10.0)
    assert r["by_shape"]["sphere"]["position_error_pct"] == pytest.approx(30.0)
    assert r["by_size"]["0.7"]["position_error_pct"] == pytest.approx(10.0)
    assert r["by_size"]["1.4"]["num_objects"] == 1
    assert r["by_material"]["rubber"]["position_error_pct"] == pytest.approx(30.0)
    json.loads(json.dumps(r))  # JSON-ready: plain floats, ints, str keys
    table = format_table(r)
    assert "pos %" in table and "material rubber" in table and "horizon 1" in table


def test_multiple_objects_per_scene_weigh_equally():
    true = make_scene(resting(4, N=2), scale=1.0)
    pred = make_scene(resting(4, N=2) + np.array([[0.1, 0, 0], [0.3, 0, 0]]), scale=1.0)
    r = evaluate_scenes([pred], [true], MESHES)
    assert r["position_error_pct"] == pytest.approx(20.0) and r["num_objects"] == 2


def test_per_frame_curves_with_different_lengths():
    a = make_scene(resting(3))
    b = make_scene(resting(5))
    pb = make_scene(resting(5) + [0.2, 0, 0])
    c = per_frame_curves([a, pb], [a, b], MESHES)
    assert np.allclose(c["count"], [2, 2, 2, 1, 1])
    assert np.allclose(c["position_error_pct"], [10, 10, 10, 20, 20])


def test_mismatched_scenes_raise():
    with pytest.raises(ValueError, match="positions"):
        evaluate_scenes([make_scene(resting(4))], [make_scene(resting(5))], MESHES)
    with pytest.raises(ValueError, match="scenes"):
        evaluate_scenes([], [make_scene(resting(5))], MESHES)


def test_spin_ratio_tells_a_model_that_turns_too_little():
    # the truth turns 10 degrees a frame about a tilted axis; the prediction 6 (0.6 of it), then a
    # second object that does not turn at all in either: the group ratio is 0.6, not undefined
    axis = [0.3, -0.5, 0.8]
    true_q = np.stack([quat_from_axis_angle(axis, np.radians(10.0 * t)) for t in range(9)])
    pred_q = np.stack([quat_from_axis_angle(axis, np.radians(6.0 * t)) for t in range(9)])
    still = np.broadcast_to(IDENTITY, (9, 4))
    true = make_scene(resting(9, 2), np.stack([true_q, still], 1))
    pred = make_scene(resting(9, 2), np.stack([pred_q, still], 1))
    f = per_frame_errors(pred, true, MESHES)
    assert f["spin_deg"][0].tolist() == [0.0, 0.0]
    assert np.allclose(f["spin_deg"][1:, 0], 6.0) and np.allclose(f["true_spin_deg"][1:, 0], 10.0)
    r = evaluate_scenes([pred], [true], MESHES)
    assert r["spin_ratio"] == pytest.approx(0.6)
    assert "spin/true" in format_table(r) and "0.60" in format_table(r)
    # a prediction that turns exactly as the truth scores 1; nothing turning anywhere scores None
    assert evaluate_scenes([true], [true], MESHES)["spin_ratio"] == pytest.approx(1.0)
    assert evaluate_scenes([make_scene(resting(4))], [make_scene(resting(4))], MESHES)["spin_ratio"] is None


def test_rmse_of_a_known_offset_and_turn_and_groups_by_object_count():
    """FIGNet's metrics: a centre off by 0.3 at every frame and a turn of 10 degrees give RMSEs
    0.3 and 10; a scene whose offset grows linearly (0 .. 0.6 over 7 frames) gives the RMS of it,
    not its mean. Scenes of one and of three objects are reported apart."""
    T = 7
    true1 = make_scene(resting(T, 1))
    off = resting(T, 1) + np.array([0.3, 0.0, 0.0])
    turn = np.broadcast_to(quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(10.0)), (T, 1, 4)).copy()
    pred1 = make_scene(off, turn)
    r = evaluate_scenes([pred1], [true1], MESHES)
    assert r["translation_rmse"] == pytest.approx(0.3) and r["rotation_rmse_deg"] == pytest.approx(10.0)
    true3 = make_scene(resting(T, 3))
    ramp = resting(T, 3).copy()
    ramp[:, :, 0] += np.linspace(0.0, 0.6, T)[:, None]
    r = evaluate_scenes([pred1, make_scene(ramp)], [true1, true3], MESHES)
    rms = np.sqrt(np.mean(np.linspace(0.0, 0.6, T) ** 2))
    assert r["by_objects"]["3"]["translation_rmse"] == pytest.approx(rms)
    assert r["by_objects"]["3"]["translation_rmse"] > r["by_objects"]["3"]["position_error_pct"] / 100  # RMS > mean
    assert r["by_objects"]["1"]["num_objects"] == 1 and r["by_objects"]["3"]["num_objects"] == 3
    assert "objects 3" in format_table(r) and "RMSE over frames and objects" in format_table(r)
