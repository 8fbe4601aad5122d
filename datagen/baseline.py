"""Analytic baseline for the real cube tosses: PyBullet, identified on training tosses.

A toss is predicted the way the GNS predicts it: the first 3 measured frames are given, the
rest is simulated. The state at frame 2 is estimated from frames 0-2 alone, assuming free
flight under the model's gravity (ballistic centre, constant world-frame spin, which is exact
for a cube because its inertia is isotropic):
    v2 = (p2 - p0) / (2 dt) + a dt,   w = rotvec(R2 R0^T) / (2 dt).
The data's own velocity columns are not used: they are median filtered, so they may already
have seen later frames.

The world follows datagen/simulate.py (Kubric's settings, design.md section 3): a fresh DIRECT
client per toss, a thick box floor with its top at z = floor_z, maximal coordinates,
contactProcessingThreshold=0, no restitution velocity threshold, split impulse with
splitImpulsePenetrationThreshold=0, no damping. The cube is a GEOM_BOX (box-box contacts
are exact: it rests at z = 1 - 1e-4, where a convex-hull cube rests at 1 + its 0.001 margin) with
a uniform solid cube's inertia (2/3 m a^2, a = half-width). PyBullet does not care about units:
everything runs in the data's half-widths and seconds (nominal gravity 187.21 half-widths/s^2).
Bullet's absolute lengths (collision margin 0.001, contact breaking threshold 0.02) are then
thousandths of the cube, as they would be for a ~1 m object in metres.

Bullet multiplies the two bodies' coefficients, so the floor has friction 1 and restitution 1
and the cube carries the identified values. Parameters (BaselineParams):
  friction, restitution  the Coulomb friction and restitution of the cube-table contact;
  stiffness, damping_ratio  a compliant contact (changeDynamics contactStiffness k and
    contactDamping 2 zeta sqrt(k m)); stiffness 0 keeps Bullet's rigid contact;
  rolling_friction, spinning_friction  Bullet's rolling and torsional friction (lever arms);
  gravity  its magnitude (fit_gravity measures the data's own: ~2% below the nominal value);
  floor_z  the table's height (fit_floor measures it: the data's cube rests 0.022 low);
  substeps  physics steps per 148 Hz frame (physics at 148 * substeps Hz);
  solver_iterations, contact_erp  the sequential-impulse solver's iterations and its position
    correction for rigid contacts.
`fit_parameters` identifies the FIT names of BOUNDS on training tosses with `identify`, which
is engine-neutral (datagen/baseline_mujoco.py uses it too): `fit_gravity` and `fit_floor`
measure gravity and the table height, then a seeded Latin hypercube over the searched box
and bounded Nelder-Mead from its best few points minimise the pipeline's own metric
(`objective`) on the training tosses.

This module scores its own objective with a local copy of the metric formulas, because datagen
must not import gns; tests check the copy against gns.metrics.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from .contactnets import DEFAULTS as CONTACTNETS
from .shards import Scene
from .simulate import FLOOR_HALF_WIDTH, _wxyz, _xyzw, pb

FRAME_RATE = 1.0 / CONTACTNETS["dt"]          # 148 Hz
GRAVITY = float(CONTACTNETS["g"])             # half-widths / s^2
GIVEN = 3                                     # measured frames given, as for the GNS
UNIT_CUBE_HALF = 0.5                          # the `cube` asset spans +-0.5 before scaling
# One degree of rotation error weighs as much as 0.5% of the width in the fitting objective:
# tuned engines reach ~12% and ~18-25 degrees here, so both terms count about equally.
ROTATION_WEIGHT = 0.5


@dataclass(frozen=True)
class BaselineParams:
    friction: float = float(CONTACTNETS["mu"])             # 0.18, published by ContactNets
    restitution: float = float(CONTACTNETS["restitution"])  # 0.125
    stiffness: float = 0.0       # contact stiffness (mass units / s^2); 0 = Bullet's rigid contact
    damping_ratio: float = 0.0   # contact damping as a fraction of critical, used with stiffness
    rolling_friction: float = 0.0   # Bullet's rolling and spinning (torsional) friction: a lever
    spinning_friction: float = 0.0  # arm, scene units (torque limit = value x normal force)
    gravity: float = GRAVITY     # magnitude along -z, scene units / s^2 (see fit_gravity)
    floor_z: float = 0.0         # height of the table top (see fit_floor)
    substeps: int = 4            # physics steps per frame: 592 Hz for the 148 Hz data
    solver_iterations: int = 50  # Bullet's default
    contact_erp: float = 0.0     # rigid contact's position correction per step; 0 keeps Bullet's

    def to_dict(self) -> dict:
        return asdict(self)


PUBLISHED = BaselineParams()

# What fit_parameters can search, in this order: (name, low, high); "log10_x" searches field x
# on a log10 scale, an int field is rounded. Friction is the parameter the errors hinge on (it
# sets how far a cube slides: 0.1 or 0.3 instead of 0.18 doubles the error), so its range is
# kept to what acrylic on a table can plausibly have. 10^3.5 is a soft contact (the cube visibly
# sinks), 10^7 about rigid at 592 Hz. Rolling and spinning friction are lever arms in half-widths:
# Coulomb friction at a face's corners already resists spin with ~0.18 x 1.4 = 0.25.
BOUNDS = (("friction", 0.05, 0.5), ("restitution", 0.0, 0.6),
          ("log10_stiffness", 3.5, 7.0), ("damping_ratio", 0.05, 2.0),
          ("rolling_friction", 0.0, 0.1), ("spinning_friction", 0.0, 0.3),
          ("substeps", 2, 20), ("solver_iterations", 10, 150), ("contact_erp", 0.05, 1.0))
# What the pipeline identifies: all but contact_erp, which a compliant contact (stiffness > 0,
# as every searched point is) ignores: Bullet then derives ERP and CFM from stiffness and damping.
FIT = ("friction", "restitution", "log10_stiffness", "damping_ratio", "rolling_friction", "spinning_friction",
       "substeps", "solver_iterations")


# ---- one toss --------------------------------------------------------------------------------

def _rotations(quat_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(quat_wxyz)[..., [1, 2, 3, 0]])


def initial_state(scene: Scene, frame_rate: float = FRAME_RATE, gravity: float = GRAVITY,
                  given: int = GIVEN) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    w = (_rotations(q[k]) * _rotations(q[j]).inv()).as_rotvec() / span
    return p[k].copy(), q[k] / np.linalg.norm(q[k]), v, w


def _half_extent(scene: Scene) -> float:
    if list(scene.shape) != ["cube"]:
        raise ValueError(f"the baseline simulates one cube per scene, got shapes {list(scene.shape)}")
    return UNIT_CUBE_HALF * float(scene.scale[0])


def _build(scene: Scene, params: BaselineParams, frame_rate: float, state) -> tuple[int, int]:
    c = pb.connect(pb.DIRECT)
    pb.setGravity(0.0, 0.0, -float(params.gravity), physicsClientId=c)
    pb.setPhysicsEngineParameter(
        fixedTimeStep=1.0 / (frame_rate * params.substeps), numSolverIterations=params.solver_iterations,
        numSubSteps=0, restitutionVelocityThreshold=0, warmStartingFactor=0, useSplitImpulse=True,
        contactSlop=0, splitImpulsePenetrationThreshold=0, enableConeFriction=False,
        deterministicOverlappingPairs=True, physicsClientId=c)
    if params.contact_erp > 0:
        pb.setPhysicsEngineParameter(contactERP=float(params.contact_erp), physicsClientId=c)
    box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[FLOOR_HALF_WIDTH, FLOOR_HALF_WIDTH, 1.0], physicsClientId=c)
    floor = pb.createMultiBody(0, box, basePosition=[0, 0, params.floor_z - 1.0], useMaximalCoordinates=True,
                               physicsClientId=c)
    pb.changeDynamics(floor, -1, lateralFriction=1.0, restitution=1.0, contactProcessingThreshold=0, physicsClientId=c)
    a = _half_extent(scene)
    mass = float(scene.mass[0])
    pos, quat, vel, ang = state
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[a, a, a], physicsClientId=c)
    body = pb.createMultiBody(mass, col, basePosition=pos.tolist(), baseOrientation=_xyzw(quat),
                              useMaximalCoordinates=True, physicsClientId=c)
    # mass must be passed with localInertiaDiagonal: without it this PyBullet build ignores the
    # new inertia in the solver and the cube falls through the floor.
    inertia = 2.0 / 3.0 * mass * a * a
    # Bullet combines rolling (spinning) friction as r0 mu1 + r1 mu0: with the floor's 1 and 0
    # the cube's own value is the contact's. Bullet adds the torsional (spinning) friction
    # constraint only where rolling friction is > 0, so a negligible one switches it on.
    rolling = max(float(params.rolling_friction), 1e-9 if params.spinning_friction > 0 else 0.0)
    pb.changeDynamics(body, -1, lateralFriction=float(params.friction), restitution=float(params.restitution),
                      rollingFriction=rolling,
                      spinningFriction=float(params.spinning_friction), mass=mass, localInertiaDiagonal=[inertia] * 3, linearDamping=0, angularDamping=0,
                      contactProcessingThreshold=0, physicsClientId=c)
    if params.stiffness > 0:
        damping = 2.0 * params.damping_ratio * math.sqrt(params.stiffness * mass)
        pb.changeDynamics(body, -1, contactStiffness=float(params.stiffness), contactDamping=float(damping),
                          physicsClientId=c)
    pb.resetBaseVelocity(body, vel.tolist(), ang.tolist(), physicsClientId=c)
    return c, body


def simulate_toss(scene: Scene, params: BaselineParams = PUBLISHED, frame_rate: float = FRAME_RATE,
                  given: int = GIVEN) -> Scene:
    """A predicted copy of a one-cube toss: frames 0..given-1 copied from the truth, the rest
    simulated from the state estimated on them."""
    if params.substeps < 1:
        raise ValueError("substeps must be >= 1")
    out = prediction_arrays(scene, given)
    state = initial_state(scene, frame_rate, params.gravity, given)
    c, body = _build(scene, params, frame_rate, state)
    try:
        for t in range(given, scene.num_frames):
            for _ in range(params.substeps):
                pb.stepSimulation(physicsClientId=c)
            p, q = pb.getBasePositionAndOrientation(body, physicsClientId=c)
            v, w = pb.getBaseVelocity(body, physicsClientId=c)
            out[0][t, 0], out[1][t, 0], out[2][t, 0], out[3][t, 0] = p, _wxyz(q), v, w
    finally:
        pb.disconnect(c)
    return prediction_scene(scene, out, "pybullet", params, params.restitution)


def prediction_arrays(scene: Scene, given: int = GIVEN) -> tuple[np.ndarray, ...]:
    """Position, quaternion, velocity and angular velocity arrays (T, 1, .) of a prediction, the
    first `given` frames copied from the truth; an engine fills the rest."""
    T = scene.num_frames
    arrays = (np.empty((T, 1, 3)), np.empty((T, 1, 4)), np.empty((T, 1, 3)), np.empty((T, 1, 3)))
    for a, b in zip(arrays, (scene.positions, scene.quaternions, scene.velocities, scene.angular_velocities)):
        a[:given] = b[:given]
    return arrays


def prediction_scene(scene: Scene, arrays, engine: str, params, restitution: float) -> Scene:
    """The predicted Scene from filled prediction_arrays, its quaternions kept on one cover along
    the toss (as the truth and datagen.simulate do)."""
    pos, quat, vel, ang = arrays
    flip = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=-1) < 0, -1.0, 1.0), axis=0)
    quat[1:] *= flip[..., None]
    return Scene(positions=pos, quaternions=quat, velocities=vel, angular_velocities=ang,
                 shape=list(scene.shape), material=list(scene.material), scale=scene.scale.copy(),
                 mass=scene.mass.copy(), friction=np.array([params.friction]), restitution=np.array([restitution]),
                 attrs={**scene.attrs, "baseline": engine, "params": str(params.to_dict())})


# ---- scoring and identification ---------------------------------------------------------------

def toss_errors(pred: Scene, true: Scene) -> tuple[float, float]:
    """Mean over all frames of the position error (% of the cube width) and the rotation error
    (degrees): the ContactNets metrics, the same formulas as gns.metrics."""
    width = 2.0 * _half_extent(true)
    pos = 100.0 * np.linalg.norm(pred.positions[:, 0] - true.positions[:, 0], axis=-1) / width
    a, b = pred.quaternions[:, 0], true.quaternions[:, 0]
    # r = a * conj(b); angle = 2 atan2(|vec r|, |w r|), exact near 0 unlike arccos.
    w = np.sum(a * b, axis=-1)
    vec = (-a[:, :1] * b[:, 1:] + b[:, :1] * a[:, 1:] - np.cross(a[:, 1:], b[:, 1:]))
    rot = np.degrees(2.0 * np.arctan2(np.linalg.norm(vec, axis=-1), np.abs(w)))
    return float(pos.mean()), float(rot.mean())


def lowest_corner_height(scene: Scene) -> np.ndarray:
    """Height of the cube's lowest corner at every frame (T,): p_z - a sum_j |R_zj|."""
    rot = _rotations(scene.quaternions[:, 0]).as_matrix()
    return scene.positions[:, 0, 2] - _half_extent(scene) * np.abs(rot[:, 2, :]).sum(-1)


def free_flight_frames(scene: Scene, margin: float = 0.05) -> int:
    """Number of leading frames before the lowest corner first comes within `margin` (scene
    units) of the table: the part of the toss that is free flight."""
    near = np.nonzero(lowest_corner_height(scene) < margin)[0]
    return int(near[0]) if len(near) else scene.num_frames


def fit_gravity(scenes: Sequence[Scene], frame_rate: float = FRAME_RATE, margin: float = 0.05,
                min_frames: int = 8) -> float | None:
    """Effective gravity of the data: the median over tosses of -2 x the quadratic coefficient
    of the centre height fitted on each toss's free flight (tosses with at least min_frames
    free frames). None if no toss has enough.

    On the ContactNets tosses this gives ~183.4 half-widths/s^2, 2% below the nominal 187.21
    (9.81 m/s^2 over a 5.24 cm half-width): the length or time calibration is off by that much,
    and a simulator with the nominal value drifts ~1% of the width per 0.1 s of flight.
    """
    values = []
    for sc in scenes:
        k = free_flight_frames(sc, margin)
        if k < min_frames:
            continue
        t = np.arange(k) / frame_rate
        coef = np.polyfit(t, sc.positions[:k, 0, 2], 2)
        values.append(-2.0 * coef[0])
    return float(np.median(values)) if values else None


def fit_floor(scenes: Sequence[Scene], frame_rate: float = FRAME_RATE, max_speed: float = 0.1) -> float | None:
    """Height of the table as the data see it: the median over tosses that end at rest (centre
    slower than max_speed scene units/s over their last 4 frames) of the final centre height
    minus the half-width. None if no toss ends at rest.

    The ContactNets cube rests at z ~ 0.978, not 1 (README: a motion-capture offset), so this
    gives ~ -0.022; a simulator with the table at 0 carries that 1.1% of the width as error on
    every resting frame.
    """
    values = []
    for sc in scenes:
        if sc.num_frames < 5:
            continue
        speed = np.linalg.norm(sc.positions[-1, 0] - sc.positions[-5, 0]) * frame_rate / 4
        if speed < max_speed:
            values.append(sc.positions[-1, 0, 2] - _half_extent(sc))
    return float(np.median(values)) if values else None


def first_frames(scene: Scene, frames: int | None) -> Scene:
    """The first `frames` frames of a scene (all of them if None)."""
    if frames is None or frames >= scene.num_frames:
        return scene
    return replace(scene, positions=scene.positions[:frames], quaternions=scene.quaternions[:frames],
                   velocities=scene.velocities[:frames], angular_velocities=scene.angular_velocities[:frames])


def objective(params, scenes: Sequence[Scene], frame_rate: float = FRAME_RATE,
              rotation_weight: float = ROTATION_WEIGHT, simulate: Callable | None = None,
              horizon: int | None = None) -> float:
    """Mean over tosses of position error % + rotation_weight x rotation error in degrees, over
    each toss's first `horizon` frames (all frames if None). `simulate(scene, params,
    frame_rate)` is the engine (default: this module's PyBullet)."""
    simulate = simulate or simulate_toss
    total = 0.0
    for sc in scenes:
        sc = first_frames(sc, horizon)
        pos, rot = toss_errors(simulate(sc, params, frame_rate), sc)
        total += pos + rotation_weight * rot
    return total / len(scenes)


def _field(name: str) -> str:
    return name[len("log10_"):] if name.startswith("log10_") else name


def params_from_unit(u: np.ndarray, names: Sequence[str], base, bounds) -> object:
    """base with the searched fields set from a point u of the unit cube (one entry per name)."""
    box = {n: (lo, hi) for n, lo, hi in bounds}
    values = {}
    for n, x in zip(names, np.clip(u, 0.0, 1.0)):
        lo, hi = box[n]
        v, f = lo + float(x) * (hi - lo), _field(n)
        v = 10.0 ** v if f != n else v
        values[f] = int(round(v)) if isinstance(getattr(base, f), int) else v
    return replace(base, **values)


def unit_from_params(p, names: Sequence[str], bounds) -> np.ndarray:
    """Where p lies in the unit cube of the searched names (clipped; a log field <= 0 maps to 0)."""
    box = {n: (lo, hi) for n, lo, hi in bounds}
    out = []
    for n in names:
        lo, hi = box[n]
        v = float(getattr(p, _field(n)))
        if _field(n) != n:
            v = math.log10(v) if v > 0 else lo
        out.append((v - lo) / (hi - lo))
    return np.clip(np.array(out), 0.0, 1.0)


def identify(train_scenes: Sequence[Scene], simulate: Callable, bounds, start, fit: Sequence[str],
             budget: int = 60, seed: int = 0, initial_points: int | None = None, local_starts: int = 2,
             max_tosses: int | None = None, horizon: int | None = None, identify_gravity: bool = True,
             identify_floor: bool = True, frame_rate: float = FRAME_RATE, rotation_weight: float = ROTATION_WEIGHT,
             log: Callable[[str], None] | None = None) -> dict:
    """Identify an engine's parameters on training tosses; deterministic for a given seed.

    Engine-neutral: `simulate(scene, params, frame_rate)` runs one toss, `start` is a frozen
    dataclass of the engine's parameters (with gravity and floor_z fields), `bounds` its search
    box ((name, low, high); "log10_x" searches field x on a log10 scale; int fields are rounded).

    First the constants with closed-form estimates are measured on all training tosses: gravity
    (fit_gravity) with identify_gravity, the table height (fit_floor) with identify_floor. The
    objective (see `objective`) is evaluated on every training toss, or on a seeded random
    subset of `max_tosses` of them. `budget` evaluations in all: the start point; a coarse
    stage of `initial_points` (default budget // 2) Latin-hypercube points over all searched
    names (seeded by `seed`); then bounded Nelder-Mead over the continuous names from each of
    the `local_starts` best coarse points in turn (int names such as substeps stay at that
    point's value), each with an equal share of what is left. Several local starts because the
    objective is rough: a bounce on a corner is chaotic, so one descent often stalls in a dent.
    The best point seen is returned, so the objective never ends above the start's.
    Returns {"params", "objective", "start_objective", "evaluations", "seconds", "fitted",
    "fit_tosses", "history": [(objective, params dict), ...], ...}.
    """
    if not train_scenes:
        raise ValueError("no training tosses to fit the baseline on")
    known = [n for n, _, _ in bounds]
    names = [n for n in known if n in fit]
    unknown = set(fit) - set(names)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; fittable: {', '.join(known)}")
    if budget < 1:
        raise ValueError("budget must be >= 1")
    t0 = time.perf_counter()
    measured = {"gravity": fit_gravity(train_scenes, frame_rate) if identify_gravity else None,
                "floor_z": fit_floor(train_scenes, frame_rate) if identify_floor else None}
    start = replace(start, **{k: v for k, v in measured.items() if v is not None})
    scenes = list(train_scenes)
    if max_tosses is not None and len(scenes) > max_tosses:
        pick = np.random.default_rng([seed, 1]).choice(len(scenes), max_tosses, replace=False)
        scenes = [scenes[i] for i in sorted(pick)]
    cache: dict[tuple, float] = {}
    history: list[tuple[float, dict]] = []
    best = {"value": math.inf, "params": start}
    cap = [budget]

    def evaluate(p) -> float:
        key = tuple(round(v, 12) if isinstance(v, float) else v for v in p.to_dict().values())
        if key not in cache:
            if len(cache) >= cap[0]:
                raise _BudgetSpent
            cache[key] = objective(p, scenes, frame_rate, rotation_weight, simulate, horizon)
            history.append((cache[key], p.to_dict()))
            if cache[key] < best["value"]:
                best.update(value=cache[key], params=p)
            if log:
                log(f"baseline fit {len(cache)}/{budget}: {cache[key]:.3f} at {_short(p)}")
        return cache[key]

    start_value = evaluate(start)
    coarse: list[tuple[float, np.ndarray]] = []
    try:
        n_init = budget // 2 if initial_points is None else initial_points
        if n_init > 0 and names:
            for u in qmc.LatinHypercube(len(names), seed=seed).random(n_init):
                coarse.append((evaluate(params_from_unit(u, names, start, bounds)), u))
    except _BudgetSpent:
        pass
    ints = [isinstance(getattr(start, _field(n)), int) for n in names]
    free = [i for i, is_int in enumerate(ints) if not is_int]
    seeds = [u for _, u in sorted(coarse, key=lambda c: c[0])[:max(local_starts, 0)]]
    if not seeds and names:  # no coarse stage: descend from the start
        seeds = [unit_from_params(start, names, bounds)]
    for k, u0 in enumerate(seeds if free else []):
        cap[0] = len(cache) + (budget - len(cache)) // (len(seeds) - k)
        x0 = u0[free]

        def f(x, u0=u0):
            u = u0.copy()
            u[free] = x
            return evaluate(params_from_unit(u, names, start, bounds))

        simplex = np.vstack([x0] + [np.clip(x0 + 0.15 * np.eye(len(free))[i] * (1 if x0[i] < 0.85 else -1), 0, 1)
                                    for i in range(len(free))])
        try:
            minimize(f, x0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * len(free),
                     options={"initial_simplex": simplex, "maxfev": 10 * budget, "xatol": 1e-3, "fatol": 1e-3})
        except _BudgetSpent:
            pass
    return {"params": best["params"], "objective": best["value"], "start_objective": start_value,
            "evaluations": len(cache), "seconds": time.perf_counter() - t0, "fitted": names,
            "fit_tosses": len(scenes), "horizon": horizon, "rotation_weight": rotation_weight, "history": history}


def fit_parameters(train_scenes: Sequence[Scene], budget: int = 60, seed: int = 0,
                   start: BaselineParams = PUBLISHED, fit: Sequence[str] = FIT, **kw) -> dict:
    """Identify PyBullet's parameters (the names in `fit`, of BOUNDS) on training tosses with
    `identify`; its keywords (initial_points, local_starts, max_tosses, horizon, ...) pass on."""
    if "damping_ratio" in fit and "log10_stiffness" not in fit and not start.stiffness:
        raise ValueError("damping_ratio needs log10_stiffness (it only acts on a compliant contact)")
    return identify(train_scenes, simulate_toss, BOUNDS, start, fit, budget, seed, **kw)


def baseline_engine(name: str) -> tuple[type, Callable, Callable]:
    """(parameter class, simulate_toss, fit_parameters) of an engine: "pybullet" or "mujoco"."""
    if name == "pybullet":
        return BaselineParams, simulate_toss, fit_parameters
    if name == "mujoco":
        from . import baseline_mujoco  # imports mujoco itself only when it simulates
        return baseline_mujoco.MujocoParams, baseline_mujoco.simulate_toss, baseline_mujoco.fit_parameters
    raise ValueError(f"unknown baseline engine {name!r}: pybullet or mujoco")


class _BudgetSpent(Exception):
    pass


def _short(p) -> str:
    """The searched-for values of a parameter set, for the log."""
    skip = {"gravity", "floor_z"}
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in p.to_dict().items() if k not in skip)
