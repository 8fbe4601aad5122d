"""MuJoCo baseline for the real cube tosses, identified the same way as PyBullet (baselines/pybullet.py).

The toss protocol, the start state and the scoring are baselines.toss's, the search
baselines.identify's: only the engine differs. MuJoCo is an optional extra (`pip install -e '.[mujoco]'`); without it
`simulate_toss` and `fit_parameters` raise MujocoMissing, an ImportError with one line saying so.

The world, in the data's units (half-widths, seconds): a plane with its top at floor_z and a
box of half-width a (1 for the real cube) with a uniform solid cube's inertia (MuJoCo computes
2/3 m a^2 from the box geom). One explicit contact pair carries every contact setting, so the
geoms' own defaults play no part: condim 6 (sliding, torsional and rolling friction), elliptic
friction cones, friction (sliding, sliding, torsional, rolling, rolling), solref (timeconst,
dampratio: a damped spring reaching the contact in about timeconst seconds; dampratio < 1
bounces, which is how MuJoCo gets restitution) and solimp (dmin, dmax, width, 0.5, 2: how much of
that spring is felt as the cube sinks in, from dmin at the surface to dmax at width deep).
impratio scales friction's impedance against the normal's (higher: less slip at rest).
Physics at 148 x substeps Hz with the Euler integrator and the Newton solver.

Torsional and rolling friction are lever arms in scene units: MuJoCo's defaults (0.005, 1e-4)
are for metres, so here they are thousandths of the cube; the search covers what a cube of
half-width 1 can feel.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from baselines.identify import identify
from baselines.toss import FRAME_RATE, GRAVITY, half_extent, initial_state, prediction_arrays, prediction_scene
from datagen.contactnets import DEFAULTS as CONTACTNETS
from datagen.shards import rotation
from datagen.shards import Scene
from gns.network import HISTORY


MISSING = "the MuJoCo baseline needs the mujoco package: pip install -e '.[mujoco]'"


class MujocoMissing(ImportError):
    pass


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise MujocoMissing(MISSING) from None
    return mujoco


def available() -> bool:
    try:
        _mujoco()
    except MujocoMissing:
        return False
    return True


@dataclass(frozen=True)
class MujocoParams:
    friction: float = float(CONTACTNETS["mu"])  # sliding, as published for the data
    torsional_friction: float = 0.005  # lever arm, scene units (MuJoCo's default number)
    rolling_friction: float = 1e-4     # lever arm, scene units (MuJoCo's default number)
    timeconst: float = 0.02            # solref[0], seconds (MuJoCo's default)
    dampratio: float = 1.0             # solref[1]; < 1 bounces
    dmin: float = 0.9                  # solimp[0], impedance at the surface
    dmax: float = 0.95                 # solimp[1], impedance at `width` deep
    width: float = 0.001               # solimp[2], scene units
    impratio: float = 1.0
    gravity: float = GRAVITY
    floor_z: float = 0.0
    substeps: int = 10                 # physics steps per frame: 1480 Hz
    solver_iterations: int = 100       # MuJoCo's default

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT = MujocoParams()

# (name, low, high) as in baselines.pybullet.BOUNDS; "log10_x" searches x on a log10 scale, int fields
# are rounded. MuJoCo lifts a timeconst below 2 timesteps to 2 timesteps (its "refsafe").
BOUNDS = (("friction", 0.05, 0.5), ("log10_torsional_friction", -4.0, -0.5),
          ("log10_rolling_friction", -5.0, -1.0), ("log10_timeconst", -3.0, -1.3), ("dampratio", 0.05, 2.0),
          ("dmin", 0.5, 0.99), ("dmax", 0.9, 0.9999), ("log10_width", -4.0, -1.0), ("log10_impratio", 0.0, 2.0),
          ("substeps", 2, 20), ("solver_iterations", 10, 150))
FIT = ("friction", "log10_torsional_friction", "log10_rolling_friction", "log10_timeconst", "dampratio",
       "dmin", "dmax", "log10_width", "log10_impratio", "substeps")


def model_xml(params: MujocoParams, half: float, mass: float, frame_rate: float = FRAME_RATE) -> str:
    p = params
    return f"""<mujoco model="cube toss">
  <option timestep="{1.0 / (frame_rate * p.substeps)!r}" gravity="0 0 {-p.gravity!r}" cone="elliptic"
          impratio="{p.impratio!r}" iterations="{p.solver_iterations}" integrator="Euler"/>
  <worldbody>
    <geom name="table" type="plane" size="0 0 1" pos="0 0 {p.floor_z!r}" contype="0" conaffinity="0"/>
    <body name="cube">
      <freejoint/>
      <geom name="cube" type="box" size="{half!r} {half!r} {half!r}" mass="{mass!r}" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="cube" geom2="table" condim="6"
          friction="{p.friction!r} {p.friction!r} {p.torsional_friction!r} {p.rolling_friction!r} {p.rolling_friction!r}"
          solref="{p.timeconst!r} {p.dampratio!r}" solimp="{p.dmin!r} {p.dmax!r} {p.width!r} 0.5 2"/>
  </contact>
</mujoco>"""


@lru_cache(maxsize=8)
def _model(params: MujocoParams, half: float, mass: float, frame_rate: float):
    # One compiled model per parameter set: an objective evaluation runs it on every toss.
    return _mujoco().MjModel.from_xml_string(model_xml(params, half, mass, frame_rate))


def simulate_toss(scene: Scene, params: MujocoParams = DEFAULT, frame_rate: float = FRAME_RATE,
                  given: int = HISTORY) -> Scene:
    """A predicted copy of a one-cube toss (as baselines.pybullet.simulate_toss, in MuJoCo)."""
    mujoco = _mujoco()
    if params.substeps < 1:
        raise ValueError("substeps must be >= 1")
    half, mass = half_extent(scene), float(scene.mass[0])
    m = _model(params, half, mass, float(frame_rate))
    d = mujoco.MjData(m)
    pos, quat, vel, w = initial_state(scene, frame_rate, params.gravity, given)
    d.qpos[:] = np.concatenate([pos, quat])
    # A free joint's angular velocity is in the body frame.
    d.qvel[:] = np.concatenate([vel, rotation(quat).inv().apply(w)])
    out = prediction_arrays(scene, given)
    for t in range(given, scene.num_frames):
        mujoco.mj_step(m, d, nstep=params.substeps)
        q = d.qpos[3:7] / np.linalg.norm(d.qpos[3:7])
        out[0][t, 0], out[1][t, 0], out[2][t, 0] = d.qpos[:3], q, d.qvel[:3]
        out[3][t, 0] = rotation(q).apply(d.qvel[3:6])
    return prediction_scene(scene, out, "mujoco", params, float(scene.restitution[0]))


def fit_parameters(train_scenes: Sequence[Scene], budget: int = 60, seed: int = 0, start: MujocoParams = DEFAULT,
                   fit: Sequence[str] = FIT, **kw) -> dict:
    """Identify MuJoCo's parameters (the names in `fit`, of BOUNDS) on training tosses with
    baselines.identify: the same measured constants, objective and search as PyBullet's."""
    _mujoco()
    return identify(train_scenes, simulate_toss, BOUNDS, start, fit, budget, seed, **kw)
