"""The MuJoCo baseline against physics (rest, free flight, bounces) and against the toss protocol (baselines.toss)."""
import builtins
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("mujoco")  # the [mujoco] extra; the dev extra installs it

from baselines import mujoco as bm  # noqa: E402
from baselines.identify import fit_floor, fit_gravity  # noqa: E402
from baselines.toss import toss_errors  # noqa: E402
from datagen.contactnets import read_experiment, read_toss, toss_to_scene  # noqa: E402
from datagen.shards import Scene  # noqa: E402
from test_baselines_pybullet import synthetic  # noqa: E402

SRC = Path(__file__).parent / "data" / "contactnets"
DT, G = 1 / 148, 183.0


def energy(pred: Scene, g: float) -> np.ndarray:
    """Energy per unit mass: g z + |v|^2 / 2 + the cube's spin energy (inertia 2/3 a^2, a = 1)."""
    v, w = pred.velocities[:, 0], pred.angular_velocities[:, 0]
    return g * pred.positions[:, 0, 2] + 0.5 * (v * v).sum(-1) + 0.5 * (2 / 3) * (w * w).sum(-1)


def test_a_cube_dropped_flat_comes_to_rest_at_its_half_width():
    T = 200
    sc = synthetic(np.tile([0.0, 0.0, 1.3], (T, 1)), np.tile([1.0, 0, 0, 0], (T, 1)))
    pred = bm.simulate_toss(sc, replace(bm.DEFAULT, gravity=G))
    assert pred.positions[-1, 0, 2] == pytest.approx(1.0, abs=0.01)
    assert np.abs(pred.positions[-20:, 0, 2] - pred.positions[-1, 0, 2]).max() < 1e-4  # at rest
    assert np.abs(pred.positions[-1, 0, :2]).max() < 1e-6  # a flat drop does not slide
    low = bm.simulate_toss(sc, replace(bm.DEFAULT, gravity=G, floor_z=-0.03))
    assert low.positions[-1, 0, 2] == pytest.approx(pred.positions[-1, 0, 2] - 0.03, abs=1e-4)
    soft = bm.simulate_toss(sc, replace(bm.DEFAULT, gravity=G, timeconst=0.05, dmin=0.5, dmax=0.6))
    assert soft.positions[-1, 0, 2] < pred.positions[-1, 0, 2] - 1e-3  # a soft contact sinks in


def test_free_flight_is_a_parabola_with_constant_spin():
    v0, w = np.array([2.0, -1.0, 20.0]), np.array([5.0, -8.0, 3.0])
    t = np.arange(30) * DT  # 0.2 s, up and down, far above the table
    pos = np.array([0.0, 0.0, 10.0]) + v0 * t[:, None] - 0.5 * G * t[:, None] ** 2 * np.array([0, 0, 1])
    rot = Rotation.from_rotvec(w * t[:, None]) * Rotation.from_rotvec([0.3, 0.2, -0.1])
    sc = synthetic(pos, rot.as_quat()[:, [3, 0, 1, 2]])
    pred = bm.simulate_toss(sc, replace(bm.DEFAULT, gravity=G, substeps=20))
    # Semi-implicit Euler (v += a h, then x += v h) traces the parabola shifted down by g h s / 2
    # after s seconds of steps h, exactly: 0.006 half-widths after 0.18 s at 2960 Hz.
    s = t - t[2]
    lag = np.where(s > 0, 0.5 * G * s / (148 * 20), 0.0)
    np.testing.assert_allclose(pred.positions[:, 0, :2], pos[:, :2], atol=1e-9)
    np.testing.assert_allclose(pred.positions[:, 0, 2], pos[:, 2] - lag, atol=1e-9)
    pos_err, rot_err = toss_errors(pred, sc)
    assert rot_err < 0.01  # degrees: a cube's isotropic inertia keeps the spin constant
    np.testing.assert_allclose(pred.angular_velocities[-1, 0], w, atol=1e-9)


def test_a_bouncy_contact_bounces_without_gaining_energy():
    T = 150
    sc = synthetic(np.tile([0.0, 0.0, 3.0], (T, 1)), np.tile([1.0, 0, 0, 0], (T, 1)))
    bouncy = replace(bm.DEFAULT, gravity=G, dampratio=0.1, timeconst=0.005)
    pred = bm.simulate_toss(sc, bouncy)
    z = pred.positions[:, 0, 2]
    first = int(np.argmax(pred.velocities[:, 0, 2] > 0))  # first frame going up again
    assert first > 0 and z[first:].max() > 1.5, "expected a visible bounce"
    e = energy(pred, G)
    assert e[first:].max() < e[2], "the bounce gained energy"
    dead = bm.simulate_toss(sc, replace(bouncy, dampratio=1.0))
    assert dead.positions[first:, 0, 2].max() < z[first:].max() - 0.5


def test_torsional_friction_stops_a_spinning_cube_sooner():
    T = 60
    w = np.array([0.0, 0.0, 30.0])
    rot = Rotation.from_rotvec(w * (np.arange(T) * DT)[:, None])
    # A cube spinning about z while resting on a face (ballistic start: it meets the table at once).
    sc = synthetic(np.tile([0.0, 0.0, 1.0], (T, 1)), rot.as_quat()[:, [3, 0, 1, 2]])
    spin = lambda p: np.abs(bm.simulate_toss(sc, replace(bm.DEFAULT, gravity=G, **p)).angular_velocities[20, 0, 2])  # noqa: E731
    assert spin({"torsional_friction": 0.3}) < spin({"torsional_friction": 1e-4}) - 1.0


def test_same_protocol_and_scoring_as_pybullet_and_deterministic():
    consts = read_experiment(SRC)
    sc = toss_to_scene(read_toss(SRC / "tosses_processed" / "229.pt"), 229, "229.pt", consts)
    a, b = bm.simulate_toss(sc), bm.simulate_toss(sc)
    np.testing.assert_array_equal(a.positions[:3], sc.positions[:3])  # the given frames are the truth's
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.quaternions, b.quaternions)
    assert np.all(np.sum(a.quaternions[1:, 0] * a.quaternions[:-1, 0], -1) > 0)  # one quaternion cover
    assert a.attrs["baseline"] == "mujoco"
    pos, rot = toss_errors(a, sc)
    assert 0 < pos < 200 and 0 < rot < 180


def test_fit_is_deterministic_in_bounds_and_not_worse_than_its_start():
    consts = read_experiment(SRC)
    train = [toss_to_scene(read_toss(SRC / "tosses_processed" / f"{i}.pt"), i, f"{i}.pt", consts) for i in (229, 274)]
    fit = bm.fit_parameters(train, budget=5, seed=0)
    p = fit["params"]
    assert fit["evaluations"] <= 5 and fit["objective"] <= fit["start_objective"]
    assert p.gravity == fit_gravity(train) and p.floor_z == fit_floor(train)
    for name, lo, hi in bm.BOUNDS:
        v = getattr(p, name.removeprefix("log10_"))
        v = math.log10(v) if name.startswith("log10_") else v
        assert lo - 1e-9 <= v <= hi + 1e-9 or p == replace(bm.DEFAULT, gravity=p.gravity, floor_z=p.floor_z)
    again = bm.fit_parameters(train, budget=5, seed=0)
    assert again["params"] == p and again["objective"] == fit["objective"]


def test_missing_mujoco_is_one_clear_line(monkeypatch):
    real_import = builtins.__import__

    def no_mujoco(name, *args, **kwargs):
        if name == "mujoco":
            raise ImportError("No module named 'mujoco'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mujoco)
    sc = synthetic(np.tile([0.0, 0.0, 1.3], (5, 1)), np.tile([1.0, 0, 0, 0], (5, 1)))
    with pytest.raises(bm.MujocoMissing, match=r"pip install -e '\.\[mujoco\]'") as e:
        bm.simulate_toss(sc)
    assert "\n" not in str(e.value) and not bm.available()
