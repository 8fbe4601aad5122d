"""`datagen inspect`: validate a dataset folder and summarise it.

Every problem is reported as one line naming the shard and scene, so a user can act on it;
the caller exits non-zero when any is found.
"""
from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from .shards import METADATA_FILE, Dataset, Scene, read_shard
from plumbing import DataError
from plumbing import file_sha256
from .toss import floor_violations, rotate

UNIT_QUAT_TOL = 1e-6


def check_scene(sc: Scene, meshes: dict, floor, where: str, physics_dt: float = 0.0,
                measured: bool = False) -> list[str]:
    """One line per problem of a scene. `measured` (imported real data): sinking into the floor
    is what tracking gives, reported as a statistic by `inspect`, not a problem."""
    problems = []
    T, N = sc.positions.shape[:2]
    expect = {"positions": (T, N, 3), "quaternions": (T, N, 4), "velocities": (T, N, 3), "angular_velocities": (T, N, 3)}
    for k, shape in expect.items():
        a = getattr(sc, k)
        if a.shape != shape:
            problems.append(f"{where}: {k} has shape {a.shape}, expected {shape}")
        elif not np.isfinite(a).all():
            problems.append(f"{where}: {k} contains NaN or inf")
    for k in ("scale", "mass", "friction", "restitution"):
        a = getattr(sc, k)
        if a.shape != (N,):
            problems.append(f"{where}: {k} has shape {a.shape}, expected ({N},)")
        elif not np.isfinite(a).all():
            problems.append(f"{where}: {k} contains NaN or inf")
    if len(sc.shape) != N:
        problems.append(f"{where}: {len(sc.shape)} shape names for {N} objects")
    if problems:
        return problems
    if (sc.scale <= 0).any() or (sc.mass <= 0).any():
        problems.append(f"{where}: non-positive scale or mass")
    norm_err = np.abs(np.linalg.norm(sc.quaternions, axis=-1) - 1).max()
    if norm_err > UNIT_QUAT_TOL:
        problems.append(f"{where}: quaternions are not unit (off by up to {norm_err:.2e})")
    missing = sorted(set(sc.shape) - set(meshes))
    if missing:
        problems.append(f"{where}: no rest mesh for shape(s) {', '.join(missing)}")
    elif floor is not None and not measured:
        for n, frame, depth in floor_violations(sc, meshes, float(floor["z"]), physics_dt):
            problems.append(f"{where}: object {n} ({sc.shape[n]}) is {depth:.3g} below the floor at frame {frame}"
                            " (tunnelling or a solver failure)")
    return problems


def floor_penetration(sc: Scene, meshes: dict, floor_z: float) -> float:
    """Deepest vertex below the floor over the scene, as a fraction of each object's scale."""
    deepest = 0.0
    for n, name in enumerate(sc.shape):
        rest = sc.scale[n] * meshes[name][0]
        low = (rotate(sc.quaternions[:, n], rest[None])[..., 2] + sc.positions[:, n, 2:3]).min()
        deepest = max(deepest, (floor_z - float(low)) / float(sc.scale[n]))
    return deepest


def inspect(root: str | Path) -> tuple[list[str], dict]:
    """Returns (problems, summary). Problems are one line each."""
    root = Path(root)
    try:
        ds = Dataset(root)
    except DataError as e:
        return [str(e)], {}
    problems: list[str] = []
    summary = {"root": str(root), "format_version": ds.meta["format_version"], "frame_rate": ds.frame_rate,
               "gravity": ds.meta["gravity"], "seed": ds.meta.get("seed"), "splits": {}}
    shapes, materials, sizes, frames, objects = Counter(), Counter(), Counter(), Counter(), Counter()
    physics_dt = 1.0 / float(ds.meta["physics_rate"]) if ds.meta.get("physics_rate") else 0.0
    measured = ds.meta.get("source") is not None       # imported measurements, not a simulation
    soft = bool(ds.meta.get("soft_contact"))           # a soft-contact engine (MuJoCo) sinks in by design
    sinks: list[float] = []
    listed = set()
    for split, info in ds.meta["splits"].items():
        count = 0
        for path in ds.shard_paths(split):
            listed.add(path.name)
            try:
                scenes, meshes = read_shard(path)
            except DataError as e:
                problems.append(str(e))
                continue
            for m, (v, f) in meshes.items():
                if f.max(initial=-1) >= len(v) or f.min(initial=0) < 0:
                    problems.append(f"{path.name}: mesh {m} has faces indexing missing vertices")
            for i, sc in enumerate(scenes):
                scene_problems = check_scene(sc, meshes, ds.floor, f"{path.name} scene {i}", physics_dt,
                                             measured or soft)
                problems += scene_problems
                if (measured or soft) and ds.floor is not None and not scene_problems:
                    sinks.append(floor_penetration(sc, meshes, float(ds.floor["z"])))
                shapes.update(sc.shape)
                materials.update(sc.material)
                sizes.update(f"{s:g}" for s in sc.scale)
                frames[sc.num_frames] += 1
                objects[sc.num_objects] += 1
            count += len(scenes)
        if count != info["num_scenes"] and not any(str(p.name) in q for p in ds.shard_paths(split) for q in problems):
            problems.append(f"split {split}: {count} scenes in shards, metadata says {info['num_scenes']}")
        summary["splits"][split] = count
    stray = sorted(p.name for p in root.glob("*.h5") if p.name not in listed)
    if stray:
        problems.append(f"shards not listed in {METADATA_FILE}: {', '.join(stray)}")
    summary.update(shapes=dict(shapes), materials=dict(materials), sizes=dict(sizes),
                   frames_per_scene=dict(frames), objects_per_scene=dict(objects))
    if sinks:
        summary["measured_floor_penetration"] = {"median": float(np.median(sinks)), "max": float(np.max(sinks)),
                                                 "why": "soft contact" if soft and not measured else "tracking"}
    summary["fingerprint"] = ds.meta.get("fingerprint")
    recorded = ds.meta.get("checksums")
    if isinstance(recorded, dict):
        # Reported, not a problem: an edited shard can be valid data, but it is no longer the data
        # the fingerprint (and runs that recorded it) describe.
        summary["changed_shards"] = sorted(name for name, digest in recorded.items()
                                           if (root / name).is_file() and file_sha256(root / name) != digest)
    return problems, summary


def format_summary(s: dict) -> str:
    lines = [f"dataset {s['root']}: format v{s['format_version']}, {s['frame_rate']:g} fps, gravity {s['gravity']}, seed {s['seed']}"]
    lines.append("scenes: " + ", ".join(f"{k} {v}" for k, v in s["splits"].items()))
    for key in ("shapes", "materials", "sizes", "frames_per_scene", "objects_per_scene"):
        lines.append(f"{key.replace('_', ' ')}: " + json.dumps(s[key], sort_keys=True).strip("{}").replace('"', ""))
    if "measured_floor_penetration" in s:
        m = s["measured_floor_penetration"]
        lines.append(f"{'soft-contact' if m.get('why') == 'soft contact' else 'measured'} data: deepest point below "
                     f"the floor per scene, median {m['median']:.1%}, max {m['max']:.1%} of the object's scale "
                     f"({m.get('why', 'tracking')}, not a problem)")
    if s.get("fingerprint"):
        changed = s.get("changed_shards") or []
        lines.append(f"fingerprint: {s['fingerprint']}" + (
            f" (recorded; {len(changed)} shard(s) changed since: {', '.join(changed[:5])})" if changed
            else ", shards match their checksums"))
    return "\n".join(lines)
