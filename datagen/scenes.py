"""Scene specifications sampled from a config and a seed (numpy only, no PyBullet).

Each scene draws from its own generator keyed by (seed, split, scene index), so a scene does
not depend on how scenes are grouped into shards or spread over workers, and a larger dataset
made with the same seed extends a smaller one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plumbing import ConfigError
from .config import parse_objects
from .shapes import get_shape

SPLIT_KEYS = {"train": 0, "valid": 1, "test": 2}


@dataclass
class ObjectSpec:
    shape: str
    size: str
    scale: float
    material: str
    friction: float
    restitution: float
    density: float
    mass: float
    inertia: np.ndarray       # (3,) principal moments in the body frame
    position: np.ndarray      # (3,)
    quaternion: np.ndarray    # (4,) w x y z
    velocity: np.ndarray      # (3,)
    angular_velocity: np.ndarray  # (3,)


@dataclass
class SceneSpec:
    seed: int
    split: str
    index: int
    objects: list[ObjectSpec]

    @property
    def scene_id(self) -> str:
        return f"{self.split}-{self.index:06d}"


def scene_rng(seed: int, split: str, index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), SPLIT_KEYS[split], int(index)])


def random_quaternion(rng: np.random.Generator) -> np.ndarray:
    # A normalised 4D Gaussian is uniform on SO(3); w >= 0 picks one of the two covers.
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def sample_scene(cfg: dict, seed: int, split: str, index: int) -> SceneSpec:
    rng = scene_rng(seed, split, index)
    sc, sp = cfg["scene"], cfg["spawn"]
    lo, hi = parse_objects(sc["objects"])
    n = int(rng.integers(lo, hi + 1))
    low, high = np.array(sp["low"], float), np.array(sp["high"], float)
    vlow, vhigh = np.array(sp["velocity_low"], float), np.array(sp["velocity_high"], float)
    objects: list[ObjectSpec] = []
    radii: list[float] = []
    for _ in range(n):
        shape = get_shape(str(rng.choice(sc["shapes"])))
        size = str(rng.choice(sc["sizes"]))
        material = str(rng.choice(sc["materials"]))
        scale = float(cfg["sizes"][size])
        mat = cfg["materials"][material]
        radius = scale * float(np.linalg.norm(shape.vertices, axis=1).max())
        # Bounding spheres kept apart, as Kubric retries placement until nothing overlaps.
        for _try in range(int(sp["max_tries"])):
            pos = rng.uniform(low, high)
            pos[2] = max(pos[2], radius) if cfg["floor"]["enabled"] else pos[2]
            if all(np.linalg.norm(pos - o.position) > radius + r for o, r in zip(objects, radii)):
                break
        else:
            raise ConfigError(f"could not place {n} objects without overlap in the spawn box "
                              f"after {sp['max_tries']} tries; enlarge spawn.low/high or use fewer objects")
        vel = rng.uniform(vlow, vhigh) - np.array([pos[0], pos[1], 0.0])
        spin = float(sp["angular_velocity"])
        ang = rng.normal(size=3) * spin if spin > 0 else np.zeros(3)
        density = float(mat["density"])
        objects.append(ObjectSpec(
            shape=shape.name, size=size, scale=scale, material=material,
            friction=float(mat["friction"]), restitution=float(mat["restitution"]), density=density,
            mass=shape.mass(density, scale), inertia=shape.inertia_diagonal(density, scale),
            position=pos, quaternion=random_quaternion(rng), velocity=vel, angular_velocity=ang,
        ))
        radii.append(radius)
    return SceneSpec(seed=int(seed), split=split, index=int(index), objects=objects)
