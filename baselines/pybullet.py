"""PyBullet baseline for the real cube tosses, identified on training tosses.

The toss protocol (given frames, start state, score) is baselines.toss's, the identification
baselines.identify's; this module is the engine.

The world follows datagen/toss.py (Kubric's settings): a fresh DIRECT client per toss, a
thick box floor with its top at z = floor_z, maximal coordinates, contactProcessingThreshold=0,
no restitution velocity threshold, split impulse with splitImpulsePenetrationThreshold=0, no
damping. The cube is a GEOM_BOX (box-box contacts are exact: it rests at z = 1 - 1e-4, where a
convex-hull cube rests at 1 + its 0.001 margin) with a uniform solid cube's inertia (2/3 m a^2,
a = half-width). PyBullet does not care about units: everything runs in the data's half-widths
and seconds (nominal gravity 187.21 half-widths/s^2). Bullet's absolute lengths (collision
margin 0.001, contact breaking threshold 0.02) are then thousandths of the cube, as they would
be for a ~1 m object in metres.

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
`fit_parameters` identifies the FIT names of BOUNDS on training tosses with
baselines.identify.identify.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Sequence

from baselines.identify import identify
from baselines.toss import FRAME_RATE, GRAVITY, half_extent, initial_state, prediction_arrays, prediction_scene
from datagen.contactnets import DEFAULTS as CONTACTNETS
from datagen.shards import Scene
from datagen.shards import wxyz, xyzw
from datagen.toss import add_floor, new_world, pb
from gns.network import HISTORY


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
# Coulomb friction at a face's corners already resists spin with ~0.18 x 1.4 = 0.25. They are
# searched on a log scale because the fits land near the bottom of their ranges (rolling 3e-4 to
# 0.03, spinning ~0.03), where a linear Latin hypercube puts hardly any point; the low ends are
# negligible next to that Coulomb resistance.
BOUNDS = (("friction", 0.05, 0.5), ("restitution", 0.0, 0.6),
          ("log10_stiffness", 3.5, 7.0), ("damping_ratio", 0.05, 2.0),
          ("log10_rolling_friction", -4.0, -1.0), ("log10_spinning_friction", -3.0, 0.0),
          ("substeps", 2, 20), ("solver_iterations", 10, 150), ("contact_erp", 0.05, 1.0))
# What the pipeline identifies: all but contact_erp, which a compliant contact (stiffness > 0,
# as every searched point is) ignores: Bullet then derives ERP and CFM from stiffness and damping.
FIT = ("friction", "restitution", "log10_stiffness", "damping_ratio", "log10_rolling_friction",
       "log10_spinning_friction", "substeps", "solver_iterations")


def _build(scene: Scene, params: BaselineParams, frame_rate: float, state) -> tuple[int, int]:
    c = new_world((0.0, 0.0, -float(params.gravity)), 1.0 / (frame_rate * params.substeps), params.solver_iterations)
    if params.contact_erp > 0:
        pb.setPhysicsEngineParameter(contactERP=float(params.contact_erp), physicsClientId=c)
    add_floor(c, params.floor_z, 1.0, 1.0)
    a = half_extent(scene)
    mass = float(scene.mass[0])
    pos, quat, vel, ang = state
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[a, a, a], physicsClientId=c)
    body = pb.createMultiBody(mass, col, basePosition=pos.tolist(), baseOrientation=xyzw(quat).tolist(),
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
                  given: int = HISTORY) -> Scene:
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
            out[0][t, 0], out[1][t, 0], out[2][t, 0], out[3][t, 0] = p, wxyz(q), v, w
    finally:
        pb.disconnect(c)
    return prediction_scene(scene, out, "pybullet", params, params.restitution)


def fit_parameters(train_scenes: Sequence[Scene], budget: int = 60, seed: int = 0,
                   start: BaselineParams = PUBLISHED, fit: Sequence[str] = FIT, **kw) -> dict:
    """Identify PyBullet's parameters (the names in `fit`, of BOUNDS) on training tosses with
    `identify`; its keywords (initial_points, local_starts, max_tosses, horizon, ...) pass on."""
    if "damping_ratio" in fit and "log10_stiffness" not in fit and not start.stiffness:
        raise ValueError("damping_ratio needs log10_stiffness (it only acts on a compliant contact)")
    return identify(train_scenes, simulate_toss, BOUNDS, start, fit, budget, seed, **kw)
