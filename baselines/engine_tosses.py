"""Cube tosses simulated by an identified engine from perturbed starts of real tosses.

A learned simulator given 16 real tosses has seen too little to know how a cube slides to a stop
or which way it tips; an engine identified on the same 16 tosses knows that much physics, wrongly
in the details. Training the GNS first on many tosses simulated by that engine and then on the
real ones (gns train with train.init_from) gives it the engine's physics as a start and the
real data the last word. No data beyond the real training tosses is used: the engine is fitted on
them and the synthetic tosses start where they start, perturbed.

Each synthetic toss takes a random real training toss as its template: its start state (frames
0-2, baselines.toss.initial_state) turned about the vertical by a random angle (the table is
level and unbounded, so this is a symmetry), the cube's orientation replaced by a uniformly
random one with probability `random_orientation`, linear and angular speeds scaled by
U[1 - speed_jitter, 1 + speed_jitter], its height above the table by U[1 - height_jitter, 1 +
height_jitter], raised if a corner would start below the table. The three given frames are the
exact free flight into that state; the engine simulates the rest, as many frames as the template
has.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from baselines import baseline_engine
from baselines.toss import initial_state
from datagen.shards import rotation, wxyz
from datagen.shards import Scene
from gns.network import HISTORY


def _start_scene(template: Scene, p: np.ndarray, q: Rotation, v: np.ndarray, w: np.ndarray,
                 frame_rate: float, gravity: float) -> Scene:
    """A scene holding the template's length whose first HISTORY frames are free flight ending in
    the state (p, q, v, w) at frame HISTORY - 1; later frames are zeros for the engine to fill."""
    T = template.num_frames
    tau = (np.arange(HISTORY) - (HISTORY - 1)) / frame_rate                  # (HISTORY,) <= 0
    accel = np.array([0.0, 0.0, -gravity])
    pos = np.zeros((T, 1, 3))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1, 1))
    vel, ang = np.zeros((T, 1, 3)), np.zeros((T, 1, 3))
    pos[:HISTORY, 0] = p + v * tau[:, None] + 0.5 * accel * tau[:, None] ** 2
    vel[:HISTORY, 0] = v + accel * tau[:, None]
    quat[:HISTORY, 0] = wxyz((Rotation.from_rotvec(w * tau[:, None]) * q).as_quat())
    ang[:HISTORY, 0] = w
    return Scene(positions=pos, quaternions=quat, velocities=vel, angular_velocities=ang,
                 shape=list(template.shape), material=list(template.material), scale=template.scale.copy(),
                 mass=template.mass.copy(), friction=template.friction.copy(),
                 restitution=template.restitution.copy(), attrs={})


def engine_tosses(templates: Sequence[Scene], engine: str, params, count: int, seed: int, frame_rate: float,
                  gravity: float, random_orientation: float = 0.5, speed_jitter: float = 0.2,
                  floor_z: float = 0.0, height_jitter: float = 0.0) -> list[Scene]:
    """`count` tosses of one cube simulated by `engine` ("pybullet" or "mujoco") with `params`,
    started from perturbed starts of the templates (see the module doc). Deterministic in seed."""
    if count < 1 or not templates:
        raise ValueError("engine_tosses needs templates and count >= 1")
    _, simulate, _ = baseline_engine(engine)
    gravity = float(getattr(params, "gravity", gravity))  # the engine's own, as its start estimate uses
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        t = templates[int(rng.integers(len(templates)))]
        p, q_wxyz, v, w = initial_state(t, frame_rate, gravity)
        turn = Rotation.from_rotvec([0.0, 0.0, rng.uniform(0, 2 * np.pi)])
        q = rotation(q_wxyz)
        q = Rotation.random(random_state=rng) if rng.random() < random_orientation else turn * q
        p, v, w = turn.apply(p), turn.apply(v), turn.apply(w)
        v = v * rng.uniform(1 - speed_jitter, 1 + speed_jitter)
        w = w * rng.uniform(1 - speed_jitter, 1 + speed_jitter)
        if height_jitter:   # drawn only when asked, so that older datasets stay the same
            p = p + [0.0, 0.0, (p[2] - floor_z) * (rng.uniform(1 - height_jitter, 1 + height_jitter) - 1)]
        # keep every corner above the table at the start (and over the 2 frames before it)
        half = 0.5 * float(t.scale[0])
        corners = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
        start = _start_scene(t, p, q, v, w, frame_rate, gravity)
        rots = rotation(start.quaternions[:HISTORY, 0])
        lowest = min(float((rots[k].apply(corners)[:, 2] + start.positions[k, 0, 2]).min()) for k in range(HISTORY))
        if lowest < floor_z + 0.05 * half:
            p = p + [0.0, 0.0, floor_z + 0.05 * half - lowest]
            start = _start_scene(t, p, q, v, w, frame_rate, gravity)
        scene = simulate(start, params, frame_rate, HISTORY)
        scene.attrs = {"template": str(t.attrs.get("toss_id", "")), "engine": engine, "synthetic": i}
        out.append(scene)
    return out
