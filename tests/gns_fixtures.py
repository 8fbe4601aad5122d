"""A tiny analytic toss dataset for the gns tests, written in the real shard format (no PyBullet).

Cubes fly ballistically while spinning at a constant rate; when the centre falls below half the
cube's size it is reflected with a restitution factor (a crude bounce, but a discontinuity the
model has to learn, and exactly reproducible).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from datagen.scenes import get_shape
from datagen.shards import Scene, shard_name, write_metadata, write_shard
from gns.geometry import quat_from_axis_angle, quat_multiply

FRAME_RATE = 12
GRAVITY = (0.0, 0.0, -10.0)
FLOOR = {"z": 0.0, "friction": 0.3, "restitution": 0.5}
MATERIALS = {"metal": (0.4, 0.3), "rubber": (0.8, 0.7)}


def cube_meshes() -> dict:
    cube = get_shape("cube")
    return {"cube": (cube.vertices, cube.faces)}


def toss_scene(rng: np.random.Generator, frames: int, material: str, substeps: int = 20) -> Scene:
    scale = float(rng.choice([0.7, 1.4]))
    friction, restitution = MATERIALS[material]
    dt = 1.0 / (FRAME_RATE * substeps)
    p = np.array([*rng.uniform(-3, 3, 2), rng.uniform(1.5, 3.0)])
    v = np.array([*rng.uniform(-2, 2, 2), rng.uniform(0, 2)])
    axis, spin = rng.normal(size=3), rng.uniform(0.5, 3.0)
    q0 = quat_from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi))
    positions, velocities = [], []
    for _ in range(frames):
        positions.append(p.copy())
        velocities.append(v.copy())
        for _ in range(substeps):
            v = v + np.array(GRAVITY) * dt
            p = p + v * dt
            if p[2] < 0.5 * scale:
                p[2] = 0.5 * scale + (0.5 * scale - p[2]) * restitution
                v[2] = -v[2] * restitution
                v[:2] *= 1 - friction * 0.5
    t = np.arange(frames) / FRAME_RATE
    quats = quat_multiply(quat_from_axis_angle(axis, spin * t), q0)
    angular = np.tile(axis / np.linalg.norm(axis) * spin, (frames, 1))
    return Scene(positions=np.array(positions)[:, None], quaternions=quats[:, None],
                 velocities=np.array(velocities)[:, None], angular_velocities=angular[:, None],
                 shape=["cube"], material=[material], scale=np.array([scale]), mass=np.array([1.0]),
                 friction=np.array([friction]), restitution=np.array([restitution]))


def write_toss_dataset(root: str | Path, train: int = 8, valid: int = 2, frames: int = 12, seed: int = 0,
                       materials_vary: bool = False, floor: bool = True) -> Path:
    """Write train/valid splits of single-cube tosses under root; returns root."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    materials = ["metal", "rubber"] if materials_vary else ["metal"]
    splits = {}
    for split, count in (("train", train), ("valid", valid)):
        if count == 0:
            continue
        scenes = [toss_scene(rng, frames, materials[i % len(materials)]) for i in range(count)]
        name = shard_name(split, 0)
        write_shard(root / name, scenes, cube_meshes())
        splits[split] = {"num_scenes": count, "shards": [name]}
    write_metadata(root, {"frame_rate": FRAME_RATE, "gravity": list(GRAVITY), "floor": FLOOR if floor else None,
                          "materials_vary": materials_vary, "splits": splits})
    return root


def rolled_out(sim, history, graph, steps: int, poses: bool = False, **options):
    """sim.rollout with these rollout options (RolloutOptions fields) for the one rollout."""
    with sim.using(**options):
        return sim.rollout(history, graph, steps, poses=poses)
