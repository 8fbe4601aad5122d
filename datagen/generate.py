"""Plan a dataset as shards, simulate them on worker processes, write shards and metadata.

A shard is the unit of work and of writing: its content depends only on (config, seed,
split, shard index), never on the worker count. `metadata.json` is written first with
`complete: false` (so `--resume` knows the plan) and rewritten with `complete: true` last.
"""
from __future__ import annotations

import multiprocessing as mp
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import __version__
from .scenes import sample_scene
from .shapes import get_shape
from .inspect import floor_violations
from .shards import (METADATA_FILE, SPLITS, DataError, clear_dataset, dataset_files, read_shard, shard_name,
                     write_metadata, write_shard)
from .simulate import simulate, steps_per_frame


@dataclass(frozen=True)
class ShardTask:
    split: str
    shard: int
    first: int   # index of the first scene in its split
    count: int

    @property
    def name(self) -> str:
        return shard_name(self.split, self.shard)


def plan(counts: dict[str, int], per_shard: int) -> list[ShardTask]:
    tasks = []
    for split in SPLITS:
        n = counts.get(split, 0)
        for k, first in enumerate(range(0, n, per_shard)):
            tasks.append(ShardTask(split, k, first, min(per_shard, n - first)))
    return tasks


def _meshes(cfg: dict) -> dict:
    return {name: (get_shape(name).vertices, get_shape(name).faces) for name in cfg["scene"]["shapes"]}


def run_task(args) -> tuple[str, int, list[str]]:
    """Simulate and write one shard. Returns its name, scene count and ids of tunnelled scenes."""
    task, cfg, seed, out = args
    scenes = [simulate(sample_scene(cfg, seed, task.split, i), cfg) for i in range(task.first, task.first + task.count)]
    meshes = _meshes(cfg)
    floor = cfg["floor"]["enabled"]
    dt = 1.0 / float(cfg["physics"]["rate"])
    bad = [sc.attrs["scene_id"] for sc in scenes if floor and floor_violations(sc, meshes, 0.0, dt)]
    write_shard(Path(out) / task.name, scenes, meshes,
                attrs={"split": task.split, "shard": task.shard, "seed": seed, "first_scene": task.first})
    return task.name, task.count, bad


def metadata(cfg: dict, seed: int, counts: dict[str, int], tasks: list[ShardTask], complete: bool) -> dict:
    sc = cfg["scene"]
    materials = [cfg["materials"][m] for m in sc["materials"]]
    vary = len({(m["friction"], m["restitution"]) for m in materials}) > 1
    return {
        "complete": complete,
        "generator": "datagen toss",
        "generator_version": __version__,
        "seed": seed,
        "config": cfg,
        "frame_rate": float(sc["frame_rate"]),
        "physics_rate": float(cfg["physics"]["rate"]),
        "steps_per_frame": steps_per_frame(cfg),
        "num_frames": int(sc["frames"]),
        "gravity": [float(g) for g in cfg["physics"]["gravity"]],
        "floor": ({"z": 0.0, "friction": float(cfg["floor"]["friction"]),
                   "restitution": float(cfg["floor"]["restitution"])} if cfg["floor"]["enabled"] else None),
        "materials_vary": vary,
        "quaternion_order": "wxyz",
        "shapes": {n: {"num_vertices": int(len(get_shape(n).vertices)), "num_faces": int(len(get_shape(n).faces))}
                   for n in sc["shapes"]},
        "splits": {s: {"num_scenes": counts.get(s, 0), "shards": [t.name for t in tasks if t.split == s]}
                   for s in SPLITS},
    }


def _shard_ok(path: Path, count: int) -> bool:
    try:
        return len(read_shard(path)[0]) == count
    except DataError:
        return False


def prepare_output(out: Path, meta: dict, resume: bool, overwrite: bool) -> None:
    """Refuse to mix datasets: an existing folder needs --resume (same plan) or --overwrite."""
    if out.exists() and any(out.iterdir()):
        if overwrite:
            if not dataset_files(out):
                raise DataError(f"{out} exists and does not look like a dataset; refusing to delete it")
            clear_dataset(out)  # only the tool's own files: a user's notes in the folder stay
        elif resume:
            import json
            path = out / METADATA_FILE
            if not path.exists():
                raise DataError(f"cannot resume: {out} has no {METADATA_FILE}")
            old = json.loads(path.read_text())
            for key in ("config", "seed", "splits"):
                if old.get(key) != meta[key]:
                    raise DataError(f"cannot resume {out}: its {key} differs from this command's")
            for stale in out.glob(".*.tmp"):
                stale.unlink()
        else:
            raise DataError(f"output folder {out} exists and is not empty; use --resume to finish it or --overwrite to replace it")
    elif resume:
        raise DataError(f"cannot resume: {out} does not exist")
    out.mkdir(parents=True, exist_ok=True)


def generate(cfg: dict, seed: int, counts: dict[str, int], out: str | Path, workers: int = 1,
             per_shard: int = 50, resume: bool = False, overwrite: bool = False, progress: bool = True) -> dict:
    out = Path(out)
    for split, n in counts.items():
        if n < 0:
            raise DataError(f"scene count for {split} must be >= 0, got {n}")
    if sum(counts.values()) < 1:
        raise DataError("nothing to generate: give at least one scene")
    if workers < 1:
        raise DataError(f"--workers must be >= 1, got {workers}")
    if per_shard < 1:
        raise DataError(f"--scenes-per-shard must be >= 1, got {per_shard}")
    tasks = plan(counts, per_shard)
    meta = metadata(cfg, seed, counts, tasks, complete=False)
    prepare_output(out, meta, resume, overwrite)
    write_metadata(out, meta)
    todo = [t for t in tasks if not (resume and _shard_ok(out / t.name, t.count))]
    bar = tqdm(total=sum(counts.values()), initial=sum(counts.values()) - sum(t.count for t in todo),
               unit="scene", desc="toss", disable=not progress, file=sys.stderr)
    jobs = [(t, cfg, seed, str(out)) for t in todo]
    tunnelled: list[str] = []
    if workers == 1 or len(todo) <= 1:
        for job in jobs:
            _, n, bad = run_task(job)
            bar.update(n)
            tunnelled += bad
    else:
        # fork where the platform has it: a spawned worker pays ~0.5 s re-importing trimesh and
        # h5py, a fifth of a small run. Safe because the parent holds no PyBullet client.
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        with mp.get_context(method).Pool(min(workers, len(todo))) as pool:
            for _, n, bad in pool.imap_unordered(run_task, jobs):
                bar.update(n)
                tunnelled += bad
    bar.close()
    if tunnelled:
        # Kept, not dropped, so the dataset stays a function of the seed; inspect lists them.
        print(f"warning: {len(tunnelled)} scene(s) sank through the floor (objects too fast for "
              f"physics.rate; set physics.ccd=true or raise the rate): {', '.join(sorted(tunnelled)[:10])}",
              file=sys.stderr)
    meta["complete"] = True
    write_metadata(out, meta)
    return meta
