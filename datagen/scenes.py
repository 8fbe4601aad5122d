"""What a scene is: the shapes (unit meshes), the scene config (a TOML preset plus overrides, checked
against it), and scene specifications sampled from a config and a seed (numpy only, no PyBullet).

Each scene draws from its own generator keyed by (seed, split, scene index), so a scene does
not depend on how scenes are grouped into shards or spread over workers, and a larger dataset
made with the same seed extends a smaller one.
"""
from __future__ import annotations

import copy
import difflib
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh

from plumbing import config_dir, ConfigError, DEFAULT_PRESET, load_toml, parse_value, typed_value


# Unit rigid assets: convex, watertight meshes spanning +-0.5, centred on their centre of mass.
#
# The vertex counts follow the paper's meshes (Kubric's VHACD hulls have 51-64 vertices),
# except `cube`, which is the plain 8-vertex cube of the real-cube data. The rest vertices and
# faces are written into every shard so a model sees exactly the shape that was simulated.


SHAPES = ("cube", "beveled_cube", "cylinder", "sphere")


@dataclass(frozen=True)
class Shape:
    name: str
    vertices: np.ndarray  # (V, 3) float64, unit asset, centre of mass at the origin
    faces: np.ndarray     # (F, 3) int32, outward-oriented triangles
    volume: float         # of the unit asset
    inertia: np.ndarray   # (3,) principal moments of the unit asset at density 1

    def mass(self, density: float, scale: float) -> float:
        return density * self.volume * scale**3

    def inertia_diagonal(self, density: float, scale: float) -> np.ndarray:
        # Mass scales with s^3 and the squared lever arm with s^2.
        return density * self.inertia * scale**5


def _beveled_cube_points() -> np.ndarray:
    # Minkowski sum of a cube of half-width 0.45 and a sphere of radius 0.05 (Kubric's bevel),
    # sampled with 7 directions per corner octant: 3 face normals, 3 edge bisectors, 1 diagonal.
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                sign = np.array([sx, sy, sz], float)
                pts.append(sign * (0.45 + 0.05 * dirs))
    return np.concatenate(pts)


def _cylinder_points(sections: int = 32) -> np.ndarray:
    ang = 2 * np.pi * np.arange(sections) / sections
    ring = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang)], axis=1)
    top = np.column_stack([ring, np.full(sections, 0.5)])
    bottom = np.column_stack([ring, np.full(sections, -0.5)])
    return np.concatenate([top, bottom])


def _sphere_points() -> np.ndarray:
    # Poles plus 5 latitude rings of 12: the equator ring and the poles reach +-0.5 on every axis.
    pts = [[0, 0, 0.5], [0, 0, -0.5]]
    for lat in np.radians([-60, -30, 0, 30, 60]):
        for lon in np.radians(np.arange(0, 360, 30)):
            pts.append([0.5 * np.cos(lat) * np.cos(lon), 0.5 * np.cos(lat) * np.sin(lon), 0.5 * np.sin(lat)])
    return np.array(pts)


def _cube_points() -> np.ndarray:
    return np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], float)


_BUILDERS = {
    "cube": _cube_points,
    "beveled_cube": _beveled_cube_points,
    "cylinder": _cylinder_points,
    "sphere": _sphere_points,
}


@lru_cache(maxsize=None)
def get_shape(name: str) -> Shape:
    if name not in _BUILDERS:
        raise ValueError(f"unknown shape {name!r}; known shapes: {', '.join(SHAPES)}")
    hull = trimesh.convex.convex_hull(_BUILDERS[name]())
    # Symmetric by construction; recentring guards against round-off only.
    hull.apply_translation(-hull.center_mass)
    tensor = hull.moment_inertia  # at density 1
    off_diag = np.abs(tensor - np.diag(np.diag(tensor))).max()
    if off_diag > 1e-9 * np.abs(tensor).max():
        raise AssertionError(f"{name}: body axes are not principal axes (off-diagonal {off_diag:g})")
    return Shape(
        name=name,
        vertices=np.asarray(hull.vertices, dtype=np.float64),
        faces=np.asarray(hull.faces, dtype=np.int32),
        volume=float(hull.volume),
        inertia=np.diag(tensor).copy(),
    )


def parse_shapes(text: str | list[str]) -> list[str]:
    names = [s.strip() for s in (text.split(",") if isinstance(text, str) else text) if s.strip()]
    if not names:
        raise ValueError("no shapes given")
    for n in names:
        if n not in _BUILDERS:
            raise ValueError(f"unknown shape {n!r}; known shapes: {', '.join(SHAPES)}")
    return names


# Scene configuration: a TOML preset (configs/movi_a.toml) plus command-line overrides.
#
# The preset defines every key that exists; an override or user config naming an unknown key is
# an error (a typo must not silently fall back to a default). New materials and sizes may be
# added, as long as they carry the fields the built-in ones have.


# Tables whose entries a user may add to (each new entry must have the built-in entries' keys).
OPEN_TABLES = ("materials", "sizes")


def _unknown(key: str, known) -> ConfigError:
    close = difflib.get_close_matches(key.split(".")[-1], list(known), n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return ConfigError(f"unknown config key {key!r}{hint}")


def merge(base: dict, override: dict, prefix: str = "") -> dict:
    """Deep-merge override into a copy of base, refusing keys base does not define."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        key = f"{prefix}{k}"
        if prefix.rstrip(".") in OPEN_TABLES and k not in out:
            out[k] = copy.deepcopy(v)
            continue
        if k not in out:
            raise _unknown(key, out)
        if isinstance(out[k], dict):
            if not isinstance(v, dict):
                raise ConfigError(f"config key {key!r} is a table, got {v!r}")
            out[k] = merge(out[k], v, key + ".")
        else:
            out[k] = typed_value(key, v, out[k])
    return out


def apply_sets(cfg: dict, sets: list[str]) -> dict:
    for item in sets:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        dotted, value = item.split("=", 1)
        nested: dict = {}
        node = nested
        parts = dotted.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = parse_value(value.strip())
        cfg = merge(cfg, nested)
    return cfg


def load_config(path: str | Path | None = None, sets: list[str] | None = None) -> dict:
    cfg = load_toml(config_dir() / f"{DEFAULT_PRESET}.toml")
    if path is not None:
        cfg = merge(cfg, load_toml(path))
    cfg = apply_sets(cfg, sets or [])
    validate(cfg)
    return cfg


def parse_objects(spec) -> list[tuple[int, int]]:
    """'1' -> [(1, 1)]; '3-10' -> [(3, 10)]; '1,3-10' -> [(1, 1), (3, 10)]: a scene takes one of
    the comma-separated choices at random (each as likely), then a count uniform within it."""
    choices = []
    for part in str(spec).split(","):
        text = part.strip()
        try:
            lo, hi = (text.split("-", 1) if "-" in text else (text, text))
            lo, hi = int(lo), int(hi)
        except ValueError:
            raise ConfigError(f"objects must be a count, a range like 3-10 or a comma list of them like 1,3-10, "
                              f"got {spec!r}") from None
        if lo < 1 or hi < lo:
            raise ConfigError(f"objects range must satisfy 1 <= low <= high, got {spec!r}")
        choices.append((lo, hi))
    return choices


def _finite(key: str, value, low: float | None = None, high: float | None = None, strict_low: bool = False) -> None:
    values = value if isinstance(value, list) else [value]
    for x in values:
        x = float(x)
        bad = not math.isfinite(x) or (low is not None and (x <= low if strict_low else x < low)) or \
            (high is not None and x > high)
        if bad:
            rng = "" if low is None else f" {'>' if strict_low else '>='} {low:g}"
            rng += "" if high is None else f"{' and' if rng else ''} <= {high:g}"
            raise ConfigError(f"config key {key!r} must be finite{rng}, got {value!r}")


def validate(cfg: dict) -> None:
    """Check values, so a bad number fails here with its key rather than deep inside PyBullet."""
    sc, ph = cfg["scene"], cfg["physics"]
    # Physical values: a restitution above 1 gains energy, an infinite size fills shards with NaN.
    _finite("scene.frame_rate", sc["frame_rate"], 0, strict_low=True)
    _finite("physics.rate", ph["rate"], 0, strict_low=True)
    _finite("physics.gravity", ph["gravity"])
    _finite("floor.friction", cfg["floor"]["friction"], 0)
    _finite("floor.restitution", cfg["floor"]["restitution"], 0, 1)
    for k in ("low", "high", "velocity_low", "velocity_high"):
        _finite(f"spawn.{k}", cfg["spawn"][k])
    _finite("spawn.angular_velocity", cfg["spawn"]["angular_velocity"])
    for name, size in cfg["sizes"].items():
        _finite(f"sizes.{name}", size, 0, strict_low=True)
    for name, m in cfg["materials"].items():
        for k, low, high, strict in (("friction", 0, None, False), ("restitution", 0, 1, False),
                                     ("density", 0, None, True)):
            if k in m:
                _finite(f"materials.{name}.{k}", m[k], low, high, strict)
    if int(sc["frames"]) < 4:
        raise ConfigError(f"scene.frames must be >= 4 (a GNS window needs 4), got {sc['frames']}")
    if not float(sc["frame_rate"]) > 0:
        raise ConfigError(f"scene.frame_rate must be positive, got {sc['frame_rate']}")
    if not float(ph["rate"]) > 0:
        raise ConfigError(f"physics.rate must be positive, got {ph['rate']}")
    ratio = float(ph["rate"]) / float(sc["frame_rate"])
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ConfigError(f"physics.rate ({ph['rate']}) must be a whole multiple of scene.frame_rate ({sc['frame_rate']})")
    if len(ph["gravity"]) != 3:
        raise ConfigError("physics.gravity must have 3 components")
    if int(ph["solver_iterations"]) < 1:
        raise ConfigError("physics.solver_iterations must be >= 1")
    if cfg["floor"].get("body", "box") not in ("box", "plane"):
        raise ConfigError(f"floor.body must be box or plane, got {cfg['floor']['body']!r}")
    parse_objects(sc["objects"])
    try:
        parse_shapes(sc["shapes"])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    for name in sc["sizes"]:
        if name not in cfg["sizes"]:
            raise ConfigError(f"unknown size {name!r}; known sizes: {', '.join(cfg['sizes'])}")
        if not float(cfg["sizes"][name]) > 0:
            raise ConfigError(f"size {name!r} must be positive, got {cfg['sizes'][name]}")
    for name in sc["materials"]:
        if name not in cfg["materials"]:
            raise ConfigError(f"unknown material {name!r}; known materials: {', '.join(cfg['materials'])}")
    for name, m in cfg["materials"].items():
        for k in ("friction", "restitution", "density"):
            if k not in m:
                raise ConfigError(f"material {name!r} lacks {k!r}")
        if not float(m["density"]) > 0:
            raise ConfigError(f"material {name!r}: density must be positive")
        if float(m["friction"]) < 0 or not 0 <= float(m["restitution"]) <= 1:
            raise ConfigError(f"material {name!r}: need friction >= 0 and 0 <= restitution <= 1")
    sp = cfg["spawn"]
    for a, b in (("low", "high"), ("velocity_low", "velocity_high")):
        if len(sp[a]) != 3 or len(sp[b]) != 3 or any(float(x) > float(y) for x, y in zip(sp[a], sp[b])):
            raise ConfigError(f"spawn.{a} must be <= spawn.{b} componentwise (3 values each)")
    if cfg["floor"]["enabled"] and float(sp["low"][2]) < 0:
        raise ConfigError("spawn.low z must be >= 0 (above the floor)")


# the physics floor: a box this wide each way from the origin (datagen.toss.add_floor)
FLOOR_HALF_WIDTH = 1000.0


def check_floor_covers(cfg: dict) -> None:
    """Refuse a spawn box the physics floor (a box of half-width FLOOR_HALF_WIDTH) does not cover:
    the metadata declares a floor everywhere, so objects beyond its edge would fall through what
    the data calls a floor. (A wider box is no answer: contact precision falls with its size.)"""
    if not cfg["floor"]["enabled"]:
        return
    sp = cfg["spawn"]
    reach = max(float(cfg["sizes"][n]) for n in cfg["scene"]["sizes"]) * max(
        float(np.linalg.norm(get_shape(n).vertices, axis=1).max()) for n in cfg["scene"]["shapes"])
    far = max(abs(float(v)) for corner in (sp["low"], sp["high"]) for v in corner[:2])
    if far + reach > FLOOR_HALF_WIDTH:
        raise ConfigError(f"spawn.low/high reach {far:g} from the origin, beyond the physics floor "
                          f"(|x|, |y| <= {FLOOR_HALF_WIDTH:g}); keep the spawn box within it or set floor.enabled=false")
    # Where a toss can fly in the scene's time, before anything is simulated: the start velocity is
    # u - x (u in the velocity box, towards the centre), and nothing but friction and collisions acts
    # sideways, so x + (u - x) t bounds the travel; it is linear in x, u and t, so corners suffice.
    t_end = float(cfg["scene"]["frames"]) / float(cfg["scene"]["frame_rate"])
    flown = max(abs(float(x) + (float(u) - float(x)) * t_end)
                for k in (0, 1) for x in (sp["low"][k], sp["high"][k])
                for u in (sp["velocity_low"][k], sp["velocity_high"][k]))
    if flown + reach > FLOOR_HALF_WIDTH:
        raise ConfigError(f"tosses from the spawn box can fly {flown:g} from the origin within the scene's "
                          f"{t_end:g} s, beyond the physics floor (|x|, |y| <= {FLOOR_HALF_WIDTH:g}); shrink the "
                          "spawn box or the velocity box, or shorten the scenes")


# Scene specifications: each scene its own generator, so it does not depend on the grouping.

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
    choices = parse_objects(sc["objects"])
    # a single choice draws nothing for it: scenes of a count or a range stay what they always were
    lo, hi = choices[int(rng.integers(len(choices)))] if len(choices) > 1 else choices[0]
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
