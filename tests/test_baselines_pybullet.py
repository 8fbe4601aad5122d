"""The PyBullet baseline for real cube tosses, on the three real tosses in tests/data."""
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from baselines import toss
from baselines.identify import (fit_floor, fit_gravity, free_flight_frames, objective, params_from_unit,
                                unit_from_params)
from baselines.pybullet import BOUNDS, FIT, PUBLISHED, BaselineParams, fit_parameters, simulate_toss
from baselines.toss import initial_state, toss_errors
from datagen.contactnets import read_experiment, read_toss, toss_to_scene
from datagen.scenes import get_shape
from datagen.shards import Scene
from gns.metrics import evaluate_scenes

SRC = Path(__file__).parent / "data" / "contactnets"
CUBE = get_shape("cube")
MESHES = {"cube": (CUBE.vertices, CUBE.faces)}


@pytest.fixture(scope="module")
def tosses():
    consts = read_experiment(SRC)
    return {i: toss_to_scene(read_toss(SRC / "tosses_processed" / f"{i}.pt"), i, f"{i}.pt", consts)
            for i in (55, 229, 274)}


def synthetic(positions, quaternions):
    T = len(positions)
    z = np.zeros((T, 1, 3))
    return Scene(positions=np.asarray(positions, float).reshape(T, 1, 3),
                 quaternions=np.asarray(quaternions, float).reshape(T, 1, 4), velocities=z,
                 angular_velocities=z, shape=["cube"], material=["acrylic"], scale=np.array([2.0]),
                 mass=np.array([0.37]), friction=np.array([0.18]), restitution=np.array([0.125]))


def test_published_constants_are_the_defaults():
    consts = read_experiment(SRC)
    assert BaselineParams() == PUBLISHED
    assert PUBLISHED.friction == consts["mu"] == 0.18 and PUBLISHED.restitution == consts["restitution"] == 0.125
    assert PUBLISHED.gravity == pytest.approx(consts["g"]) and PUBLISHED.stiffness == 0.0
    assert toss.FRAME_RATE == pytest.approx(148.0)


def test_initial_state_is_exact_for_a_ballistic_spinning_cube():
    dt, g = 1 / 148, 183.0
    v0, w = np.array([3.0, -2.0, 1.5]), np.array([4.0, -7.0, 2.0])
    t = np.arange(5) * dt
    pos = np.array([1.0, 2.0, 4.0]) + v0 * t[:, None] - 0.5 * g * t[:, None] ** 2 * np.array([0, 0, 1])
    rot = Rotation.from_rotvec(w * t[:, None]) * Rotation.from_rotvec([0.3, 0.2, -0.1])
    quat = rot.as_quat()[:, [3, 0, 1, 2]]
    p, q, v, omega = initial_state(synthetic(pos, quat), 148.0, g)
    np.testing.assert_allclose(p, pos[2])
    np.testing.assert_allclose(q, quat[2])
    np.testing.assert_allclose(v, v0 - np.array([0, 0, g]) * t[2], atol=1e-9)
    np.testing.assert_allclose(omega, w, atol=1e-9)


def test_free_flight_of_a_real_toss_is_reproduced_within_1_percent_of_the_width(tosses):
    for i in (229, 274):
        sc = tosses[i]
        k = free_flight_frames(sc, margin=0.05)
        assert k >= 10, f"toss {i}: expected a free flight of at least 10 frames"
        params = replace(PUBLISHED, gravity=fit_gravity([sc]))
        pred = simulate_toss(sc, params)
        np.testing.assert_array_equal(pred.positions[:3], sc.positions[:3])
        err = 100 * np.linalg.norm(pred.positions[:k, 0] - sc.positions[:k, 0], axis=-1) / 2.0
        assert err.max() < 1.0, f"toss {i}: free-flight error {err.max():.2f}% of the width"


def test_measured_gravity_and_table_height(tosses):
    g = fit_gravity(list(tosses.values()))
    assert 0.95 * PUBLISHED.gravity < g < PUBLISHED.gravity  # the data fall ~2% slower than 9.81 m/s^2
    floor = fit_floor(list(tosses.values()))
    assert -0.04 < floor < -0.01  # the measured cube rests at z ~ 0.978
    sc = tosses[55]
    moving = replace(sc, positions=sc.positions[:20], quaternions=sc.quaternions[:20])  # still in the air
    assert fit_floor([moving]) is None and fit_gravity([moving], min_frames=50) is None


def test_a_cube_dropped_flat_rests_at_its_half_width_above_the_table():
    T = 150
    sc = synthetic(np.tile([0.0, 0.0, 1.2], (T, 1)), np.tile([1.0, 0, 0, 0], (T, 1)))
    pred = simulate_toss(sc, PUBLISHED)
    assert pred.positions[-1, 0, 2] == pytest.approx(1.0, abs=1e-3)
    low = simulate_toss(sc, replace(PUBLISHED, floor_z=-0.03))
    assert low.positions[-1, 0, 2] == pytest.approx(0.97, abs=1e-3)
    soft = simulate_toss(sc, replace(PUBLISHED, stiffness=1e4, damping_ratio=1.0))
    assert soft.positions[-1, 0, 2] < pred.positions[-1, 0, 2] - 1e-3  # a soft contact sinks in


def test_parameters_change_the_outcome_only_after_contact(tosses):
    sc = tosses[274]
    k = free_flight_frames(sc, margin=0.01)
    dead = simulate_toss(sc, replace(PUBLISHED, restitution=0.0))
    bouncy = simulate_toss(sc, replace(PUBLISHED, restitution=0.5))
    np.testing.assert_allclose(dead.positions[:k], bouncy.positions[:k], atol=1e-9)
    assert np.abs(dead.positions[:, 0, 2] - bouncy.positions[:, 0, 2]).max() > 0.05
    slippery = simulate_toss(sc, replace(PUBLISHED, friction=0.05))
    assert np.abs(slippery.positions[-1, 0, :2] - dead.positions[-1, 0, :2]).max() > 0.05


def test_simulation_is_deterministic(tosses):
    sc = tosses[55]
    a, b = simulate_toss(sc), simulate_toss(sc)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.quaternions, b.quaternions)


def test_toss_errors_match_gns_metrics(tosses):
    sc = tosses[229]
    pred = simulate_toss(sc, replace(PUBLISHED, friction=0.4))
    pos, rot = toss_errors(pred, sc)
    ref = evaluate_scenes([pred], [sc], MESHES)
    assert pos == pytest.approx(ref["position_error_pct"], rel=1e-12)
    assert rot == pytest.approx(ref["rotation_error_deg"], rel=1e-9)
    assert pos > 1 and rot > 1


def test_fit_on_two_tosses_stays_in_bounds_and_does_not_get_worse(tosses):
    train = [tosses[229], tosses[274]]
    fit = fit_parameters(train, budget=6, seed=0)
    p = fit["params"]
    assert fit["evaluations"] <= 6 and len(fit["history"]) == fit["evaluations"]
    assert math.isfinite(fit["objective"]) and fit["objective"] <= fit["start_objective"]
    lows, highs = {n: lo for n, lo, _ in BOUNDS}, {n: hi for n, _, hi in BOUNDS}
    if p.stiffness > 0:
        assert lows["log10_stiffness"] <= math.log10(p.stiffness) <= highs["log10_stiffness"]
        assert lows["damping_ratio"] <= p.damping_ratio <= highs["damping_ratio"]
    assert lows["friction"] <= p.friction <= highs["friction"]
    assert lows["restitution"] <= p.restitution <= highs["restitution"]
    assert p.gravity == fit_gravity(train) and p.floor_z == fit_floor(train)
    assert objective(p, train) == pytest.approx(fit["objective"], rel=1e-12)  # what it reports is what it found
    again = fit_parameters(train, budget=6, seed=0)
    assert again["params"] == p and again["objective"] == fit["objective"]


def test_spinning_friction_slows_a_spinning_cube_even_without_rolling_friction():
    T, w = 60, np.array([0.0, 0.0, 30.0])
    rot = Rotation.from_rotvec(w * (np.arange(T) / 148)[:, None])
    sc = synthetic(np.tile([0.0, 0.0, 1.0], (T, 1)), rot.as_quat()[:, [3, 0, 1, 2]])  # spinning on a face
    spin = lambda **p: abs(simulate_toss(sc, replace(PUBLISHED, **p)).angular_velocities[20, 0, 2])  # noqa: E731
    free = spin()
    assert free > 10  # Coulomb friction alone slows it only a little in 0.13 s
    assert spin(spinning_friction=0.3) < free - 5  # Bullet applies it only with rolling friction > 0
    assert spin(spinning_friction=0.3, rolling_friction=0.01) < free - 5


def test_unit_cube_mapping_covers_log_and_integer_fields():
    names = ["friction", "log10_stiffness", "substeps"]
    p = params_from_unit(np.array([0.5, 1.0, 0.5]), names, PUBLISHED, BOUNDS)
    box = {n: (lo, hi) for n, lo, hi in BOUNDS}
    assert p.friction == pytest.approx(sum(box["friction"]) / 2)
    assert p.stiffness == pytest.approx(10 ** box["log10_stiffness"][1])
    assert isinstance(p.substeps, int) and p.substeps == round(sum(box["substeps"]) / 2)
    assert p.restitution == PUBLISHED.restitution  # not searched: kept
    np.testing.assert_allclose(unit_from_params(p, names, BOUNDS)[:2], [0.5, 1.0])
    assert unit_from_params(PUBLISHED, ["log10_stiffness"], BOUNDS)[0] == 0.0  # rigid (0) maps to the low end
    arms = ["log10_rolling_friction", "log10_spinning_friction"]
    assert set(arms) <= set(FIT)  # lever arms on a log scale: the small values that fit best get sampled
    p = params_from_unit(np.array([0.0, 0.5]), arms, PUBLISHED, BOUNDS)
    assert p.rolling_friction == pytest.approx(10 ** box[arms[0]][0])
    assert p.spinning_friction == pytest.approx(10 ** (sum(box[arms[1]]) / 2))


def test_fit_on_a_subset_with_local_starts_is_deterministic(tosses):
    train = [tosses[55], tosses[229], tosses[274]]
    kw = dict(budget=9, seed=3, initial_points=4, local_starts=2, max_tosses=2, fit=["friction", "substeps"])
    fit = fit_parameters(train, **kw)
    assert fit["fit_tosses"] == 2 and fit["evaluations"] == 9  # the descents spent what the coarse stage left
    values = [h[0] for h in fit["history"]]
    assert fit["objective"] == min(values) <= values[0] == fit["start_objective"]
    substeps = {h[1]["substeps"] for h in fit["history"][5:]}
    assert len(substeps) <= 2  # each descent keeps its coarse point's substeps
    assert all(isinstance(h[1]["substeps"], int) and 2 <= h[1]["substeps"] <= 20 for h in fit["history"][1:])
    again = fit_parameters(train, **kw)
    assert again["params"] == fit["params"] and again["history"] == fit["history"]
    assert "solver_iterations" in FIT and "contact_erp" not in FIT


def test_bad_input_is_refused(tosses):
    with pytest.raises(ValueError, match="no training tosses"):
        fit_parameters([], budget=3)
    with pytest.raises(ValueError, match="unknown parameter"):
        fit_parameters([tosses[55]], fit=["friction", "mass"])
    sc = tosses[55]
    sphere = Scene(sc.positions, sc.quaternions, sc.velocities, sc.angular_velocities, ["sphere"], ["x"],
                   sc.scale, sc.mass, sc.friction, sc.restitution)
    with pytest.raises(ValueError, match="one cube"):
        simulate_toss(sphere)


def test_a_long_start_estimates_the_state_after_a_bounce_not_across_it():
    from datagen.shards import Scene
    rate, g = 100.0, 10.0
    t = np.arange(20) / rate
    z = 1.0 + 2.0 * t - 0.5 * g * t ** 2          # flying up at 2 units/s ...
    z[10:] = z[9] - 1.0 * (t[10:] - t[9]) - 0.5 * g * (t[10:] - t[9]) ** 2   # ... then knocked downwards
    pos = np.stack([0 * t, 0 * t, z], 1)[:, None]
    quat = np.tile([1.0, 0, 0, 0], (20, 1))[:, None]
    sc = Scene(pos, quat, np.zeros_like(pos), np.zeros_like(pos), ["cube"], ["acrylic"], np.ones(1), np.ones(1),
               np.ones(1), np.ones(1))
    _, _, v, _ = initial_state(sc, rate, g, given=17)
    assert abs(v[2] - (-1.0 - g * (t[16] - t[9]))) < 1e-9      # the velocity at frame 16, after the kink
