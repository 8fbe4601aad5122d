"""The toss protocol every engine baseline follows, and its score.

A toss is predicted the way the GNS predicts it: the first HISTORY (3) measured frames are
given, the rest is simulated. The state at frame 2 is estimated from frames 0-2 alone, assuming free
flight under the model's gravity (ballistic centre, constant world-frame spin, which is exact
for a cube because its inertia is isotropic):
    v2 = (p2 - p0) / (2 dt) + a dt,   w = rotvec(R2 R0^T) / (2 dt).
The data's own velocity columns are not used: they are median filtered, so they may already
have seen later frames.

Everything runs in the data's units: the ContactNets cube's half-widths and seconds. The score
(`toss_errors`) is a local copy of the metric formulas, so that an engine's fitting loop need not
build meshes; tests check the copy against gns.metrics.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from plumbing import DataError
from datagen.contactnets import DEFAULTS as CONTACTNETS
from datagen.shards import continuous, rotation
from datagen.shards import Scene
from gns.network import HISTORY

FRAME_RATE = 1.0 / CONTACTNETS["dt"]          # 148 Hz
GRAVITY = float(CONTACTNETS["g"])             # half-widths / s^2
UNIT_CUBE_HALF = 0.5                          # the `cube` asset spans +-0.5 before scaling


def initial_state(scene: Scene, frame_rate: float = FRAME_RATE, gravity: float = GRAVITY,
                  given: int = HISTORY) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """State at the last given frame k = given-1 from frames k-2..k, as free flight.

    Returns position (3,), quaternion wxyz (4,), linear and world-frame angular velocity (3,).
    """
    if scene.num_frames < given or given < 2:
        raise ValueError(f"need at least {max(given, 2)} frames to estimate the initial state")
    dt, k = 1.0 / frame_rate, given - 1
    # From the last 3 given frames (or 2): a longer start (to match what a strided GNS is given)
    # may hold a bounce, across which a secant from frame 0 would be no velocity at all.
    j = max(0, k - 2)
    p, q = scene.positions[:, 0], scene.quaternions[:, 0]
    span = (k - j) * dt
    accel = np.array([0.0, 0.0, -gravity])
    # For a ballistic centre p(t) = p_k + v (t - t_k) + a (t - t_k)^2 / 2 the secant from frame j
    # to k plus a * span / 2 is exactly v; for 3 frames it is also the least-squares slope.
    v = (p[k] - p[j]) / span + accel * span / 2.0
    w = (rotation(q[k]) * rotation(q[j]).inv()).as_rotvec() / span
    return p[k].copy(), q[k] / np.linalg.norm(q[k]), v, w


def half_extent(scene: Scene) -> float:
    if list(scene.shape) != ["cube"]:
        raise ValueError(f"the baseline simulates one cube per scene, got shapes {list(scene.shape)}")
    return UNIT_CUBE_HALF * float(scene.scale[0])


def prediction_arrays(scene: Scene, given: int = HISTORY) -> tuple[np.ndarray, ...]:
    """Position, quaternion, velocity and angular velocity arrays (T, 1, .) of a prediction, the
    first `given` frames copied from the truth; an engine fills the rest."""
    T = scene.num_frames
    arrays = (np.empty((T, 1, 3)), np.empty((T, 1, 4)), np.empty((T, 1, 3)), np.empty((T, 1, 3)))
    for a, b in zip(arrays, (scene.positions, scene.quaternions, scene.velocities, scene.angular_velocities)):
        a[:given] = b[:given]
    return arrays


def prediction_scene(scene: Scene, arrays, engine: str, params, restitution: float) -> Scene:
    """The predicted Scene from filled prediction_arrays, its quaternions kept on one cover along
    the toss (as the truth and datagen.toss do)."""
    pos, quat, vel, ang = arrays
    return Scene(positions=pos, quaternions=continuous(quat), velocities=vel, angular_velocities=ang,
                 shape=list(scene.shape), material=list(scene.material), scale=scene.scale.copy(),
                 mass=scene.mass.copy(), friction=np.array([params.friction]), restitution=np.array([restitution]),
                 attrs={**scene.attrs, "baseline": engine, "params": str(params.to_dict())})


def toss_errors(pred: Scene, true: Scene) -> tuple[float, float]:
    """Mean over all frames of the position error (% of the cube width) and the rotation error
    (degrees): the ContactNets metrics, the same formulas as gns.metrics."""
    width = 2.0 * half_extent(true)
    pos = 100.0 * np.linalg.norm(pred.positions[:, 0] - true.positions[:, 0], axis=-1) / width
    a, b = pred.quaternions[:, 0], true.quaternions[:, 0]
    # r = a * conj(b); angle = 2 atan2(|vec r|, |w r|), exact near 0 unlike arccos.
    w = np.sum(a * b, axis=-1)
    vec = (-a[:, :1] * b[:, 1:] + b[:, :1] * a[:, 1:] - np.cross(a[:, 1:], b[:, 1:]))
    rot = np.degrees(2.0 * np.arctan2(np.linalg.norm(vec, axis=-1), np.abs(w)))
    return float(pos.mean()), float(rot.mean())


def first_frames(scene: Scene, frames: int | None) -> Scene:
    """The first `frames` frames of a scene (all of them if None)."""
    if frames is None or frames >= scene.num_frames:
        return scene
    return replace(scene, positions=scene.positions[:frames], quaternions=scene.quaternions[:frames],
                   velocities=scene.velocities[:frames], angular_velocities=scene.angular_velocities[:frames])


def evaluate_baseline(data: str | Path, split: str = "test", params=None, limit: int | None = None,
                      plots_dir: str | Path | None = None, engine: str = "pybullet",
                      given: int = HISTORY) -> tuple[dict, list, list, object]:
    """gns.evaluate.evaluate_run for an analytic baseline ("pybullet" or "mujoco"): every
    one-cube scene of a split simulated from its first `given` frames with `params` (default: the
    engine's defaults, for PyBullet the published ContactNets constants), scored the same way.
    Returns (results, predicted, true, dataset)."""
    from baselines import baseline_engine  # the engines only when asked for
    from gns.evaluate import load_split, score_predictions
    params_class, simulate, _ = baseline_engine(engine)
    params = params_class() if params is None else params
    ds, scenes = load_split(data, split, limit)
    t0 = time.perf_counter()
    try:
        pred = [simulate(sc, params, frame_rate=ds.frame_rate, given=given) for sc in scenes]
    except ValueError as e:
        raise DataError(f"{data}: {e}") from None
    results = score_predictions(pred, scenes, ds, time.perf_counter() - t0, plots_dir)
    results.update(baseline=engine, params=params.to_dict(), data=str(data), split=split, given_frames=given)
    return results, pred, scenes, ds
