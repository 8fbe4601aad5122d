"""Edge-balanced drops (the paper's Fig. 3 diagnostic): a cube standing on one edge, tilted.

The edge lies along the y axis at x = 0 on the floor. At tilt 0 the cube rests on its face in
x >= 0; tilt a rotates it about that edge, lifting the face, so the centre sits at polar angle
45 + a degrees seen from the edge. Below 45 degrees the centre is over x > 0 and the cube falls
back onto that face; above 45 it is over x < 0 and it falls over the edge. 45 - d and 45 + d are
mirror images (x -> -x), so a simulator with the floor's symmetry lands them on opposite sides.

`side` reads a recorded scene: +1 when the cube ended on x > 0 ("back"), -1 on x < 0 ("over"),
0 when its centre is still within a quarter of its size of the edge (it has not fallen).
"""
from __future__ import annotations

import numpy as np

from .scenes import ObjectSpec, SceneSpec, scene_rng, sample_scene
from .scenes import get_shape

UNDECIDED_FRACTION = 0.25  # of the size: a fallen cube's centre is half its size from the edge


def tilt_quaternion(angle_deg: float) -> np.ndarray:
    """wxyz rotation by `angle_deg` about -y: the x-z plane turned from x toward z."""
    h = np.radians(angle_deg) / 2
    return np.array([np.cos(h), 0.0, -np.sin(h), 0.0])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    # Written out, as is the quaternion product in training_scene, rather than scipy's: the
    # scenes must come out bit for bit as before (an exact 45-degree tilt is a knife edge), and
    # scipy rounds differently in the last bit.
    w, u = q[0], q[1:]
    return v + 2 * np.cross(u, np.cross(u, v) + w * v)


def tilted_object(cfg: dict, angle_deg: float, shape: str = "cube", size: str = "large",
                  material: str = "metal", height: float = 0.0, offset=(0.0, 0.0)) -> ObjectSpec:
    """A cube of `cfg`'s size and material on its edge (x = offset[0]), tilted `angle_deg`,
    at rest, its lowest vertex `height` above the floor."""
    s = get_shape(shape)
    scale = float(cfg["sizes"][size])
    mat = cfg["materials"][material]
    q = tilt_quaternion(angle_deg)
    # The unit asset's edge at (-0.5, *, -0.5) is the pivot: the centre sits at +0.5, +0.5 from it.
    position = _rotate(q, np.array([0.5, 0.0, 0.5]) * scale)
    verts = np.array([_rotate(q, v) for v in s.vertices * scale]) + position
    position[2] += height - verts[:, 2].min()
    position[:2] += np.asarray(offset, float)
    density = float(mat["density"])
    return ObjectSpec(shape=shape, size=size, scale=scale, material=material, friction=float(mat["friction"]),
                      restitution=float(mat["restitution"]), density=density, mass=s.mass(density, scale),
                      inertia=s.inertia_diagonal(density, scale), position=position, quaternion=q,
                      velocity=np.zeros(3), angular_velocity=np.zeros(3))


def tilted_scene(cfg: dict, angle_deg: float, index: int = 0, split: str = "test", seed: int = 0,
                 **kwargs) -> SceneSpec:
    return SceneSpec(seed=seed, split=split, index=index, objects=[tilted_object(cfg, angle_deg, **kwargs)])


def random_tilt(rng: np.random.Generator) -> float:
    """A tilt in [0, 90] degrees, half of them within a few degrees of 45 (the hard cases)."""
    if rng.random() < 0.5:
        return float(np.clip(45.0 + rng.normal() * 3.0, 0.0, 90.0))
    return float(rng.uniform(0.0, 90.0))


def training_scene(cfg: dict, seed: int, split: str, index: int, drop_fraction: float = 0.5,
                   max_heights: tuple[float, ...] = (0.05,)) -> SceneSpec:
    """A training scene: a tilted drop (random tilt, edge direction, place, the config's shapes,
    sizes and materials, the lowest vertex uniform in [0, h] x the size above the floor, h one of
    `max_heights` at random) with probability `drop_fraction`, else a MOVi-A toss. With one
    height (the default) no draw picks it: the scenes stay those of before the parameter."""
    rng = scene_rng(seed, split, index)
    if rng.random() >= drop_fraction:
        return sample_scene(cfg, seed, split, index)
    sc = cfg["scene"]
    angle = random_tilt(rng)
    size, material = str(rng.choice(sc["sizes"])), str(rng.choice(sc["materials"]))
    shape = str(rng.choice(sc["shapes"]))
    top = float(max_heights[0]) if len(max_heights) == 1 else float(rng.choice(max_heights))
    obj = tilted_object(cfg, angle, shape=shape, size=size, material=material,
                        height=float(rng.uniform(0.0, top)) * float(cfg["sizes"][size]))
    # A random heading of the edge (turned about the vertical through the edge, at the origin)
    # and a random place on the floor.
    yaw = rng.uniform(0, 2 * np.pi)
    qz = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    obj.position = _rotate(qz, obj.position) + np.array([*rng.uniform(-3.0, 3.0, size=2), 0.0])
    w1, v1, w2, v2 = qz[0], qz[1:], obj.quaternion[0], obj.quaternion[1:]
    obj.quaternion = np.array([w1 * w2 - v1 @ v2, *(w1 * v2 + w2 * v1 + np.cross(v1, v2))])
    return SceneSpec(seed=int(seed), split=split, index=int(index), objects=[obj])


def side(positions: np.ndarray, scale: float, edge_x: float = 0.0) -> int:
    """+1 / -1 / 0: where the cube's centre ended (positions (T, 3) or (T, 1, 3)), relative to
    the edge it stood on."""
    x = float(np.asarray(positions).reshape(-1, 3)[-1, 0]) - edge_x
    if not np.isfinite(x) or abs(x) < UNDECIDED_FRACTION * scale:
        return 0
    return 1 if x > 0 else -1
