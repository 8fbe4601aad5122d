"""Plan a dataset as shards, simulate them on worker processes or a Ray cluster, write shards
and metadata.

A shard is the unit of work and of writing: its content depends only on (config, seed,
split, shard index), never on the worker count, the backend or how the shards are divided
among runs. `metadata.json` is written first with `complete: false` (so `--resume` knows the
plan), records each shard's sha256 under `written` just before the shard is renamed into place,
and is rewritten with `complete: true`, checksums and the fingerprint once every shard of the
plan is there and is the shard recorded. With `--shard-index I --num-shards K` several runs (a
Slurm array) share one folder: each writes only its shards, and whichever run sees the last
shard present finalises the metadata. Every run claims the folder first (datagen/output.py), so
runs started together cannot mix two plans; a kept shard that is not the one recorded is
refused by name, never folded into the checksums.
"""
from __future__ import annotations

import multiprocessing as mp
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from . import __version__
from plumbing import DataError
from .output import Busy, busy_error, check_output, claim, commit_shard, finalise, plan_of, start_output
from .scenes import get_shape, sample_scene
from .shards import SPLITS, shard_image, shard_name, write_error
from .simulate import FLOOR_HALF_WIDTH, check_floor_covers, floor_violations, off_floor, simulate, steps_per_frame


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


def build_task(task: ShardTask, cfg: dict, seed: int) -> tuple[bytes, list[str]]:
    """Simulate one shard in memory. Returns the shard file's bytes and ids of tunnelled scenes."""
    scenes = [simulate(sample_scene(cfg, seed, task.split, i), cfg) for i in range(task.first, task.first + task.count)]
    meshes = _meshes(cfg)
    floor = cfg["floor"]["enabled"]
    dt = 1.0 / float(cfg["physics"]["rate"])
    if floor:
        for sc in scenes:
            for n, t in off_floor(sc)[:1]:
                # the floor is declared everywhere: an object past its edge would fall through it
                raise DataError(f"scene {sc.attrs['scene_id']}: object {n} left the physics floor (|x| or |y| above "
                                f"{FLOOR_HALF_WIDTH:g}) at frame {t}; slow the tosses or shrink the spawn box")
    bad = [sc.attrs["scene_id"] for sc in scenes if floor and floor_violations(sc, meshes, 0.0, dt)]
    image = shard_image(scenes, meshes, {"split": task.split, "shard": task.shard, "seed": seed,
                                         "first_scene": task.first}, task.name)
    return image, bad


def run_task(args) -> tuple[str, int, list[str]]:
    """Simulate and write one shard. Returns its name, scene count and ids of tunnelled scenes."""
    task, cfg, seed, out, planned = args
    try:
        image, bad = build_task(task, cfg, seed)
    except OSError as e:  # HDF5 failing to build the file in memory: one line, as a failed write
        raise write_error(Path(out) / task.name, e) from None
    commit_shard(Path(out), planned, task.name, image)
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


BACKENDS = ("process", "ray")


def _check_arguments(counts: dict[str, int], workers: int, per_shard: int, backend: str,
                     ray_address: str | None = None) -> None:
    """Refuse bad counts, sizes or backend before anything is written."""
    for split, n in counts.items():
        if n < 0:
            raise DataError(f"scene count for {split} must be >= 0, got {n}")
    if sum(counts.values()) < 1:
        raise DataError("nothing to generate: give at least one scene")
    if workers < 1:
        raise DataError(f"--workers must be >= 1, got {workers}")
    if per_shard < 1:
        raise DataError(f"--scenes-per-shard must be >= 1, got {per_shard}")
    if backend not in BACKENDS:
        raise DataError(f"unknown backend {backend!r}; use {' or '.join(BACKENDS)}")
    if ray_address and backend != "ray":
        raise DataError("--ray-address needs --backend ray (the process backend runs on this machine only)")
    if backend == "ray":
        from .ray_backend import require_ray
        require_ray()


def _check_sharding(shard_index: int | None, num_shards: int | None, overwrite: bool) -> bool:
    """Whether this run is one part of a sharded generation; refuses a half-given or impossible part."""
    sharded = num_shards is not None or shard_index is not None
    if sharded:
        if num_shards is None or shard_index is None:
            raise DataError("--shard-index and --num-shards go together")
        if num_shards < 1 or not 0 <= shard_index < num_shards:
            raise DataError(f"--shard-index must be in 0..{num_shards - 1} and --num-shards >= 1, "
                            f"got {shard_index} of {num_shards}")
        if overwrite:
            raise DataError("--overwrite cannot be used with --num-shards: the runs would delete each other's "
                            "shards; clear the folder before starting them")
    return sharded


def _shard_results(todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int, ray, planned: dict):
    """Write the shards of `todo` on the chosen backend, yielding (name, count, tunnelled ids) for each."""
    jobs = [(t, cfg, seed, str(out), planned) for t in todo]
    if ray is not None and todo:
        from .ray_backend import ray_tasks
        yield from ray_tasks(ray, todo, cfg, seed, out, planned)
    elif workers == 1 or len(todo) <= 1:
        for job in jobs:
            yield run_task(job)
    else:
        # fork where the platform has it: a spawned worker pays ~0.5 s re-importing trimesh and
        # h5py, a fifth of a small run. Safe while the parent holds no PyBullet client and no
        # native threads; once torch or Ray has started theirs (a pipeline, a test run) a forked
        # child can inherit a lock held by one of them and hang, so workers then come from a
        # clean fork server
        threaded = "torch" in sys.modules or "ray" in sys.modules
        methods = mp.get_all_start_methods()
        method = ("forkserver" if threaded and "forkserver" in methods else "fork") if "fork" in methods else "spawn"
        with mp.get_context(method).Pool(min(workers, len(todo))) as pool:
            yield from pool.imap_unordered(run_task, jobs)


def _make_shards(mine: list[ShardTask], todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int,
                 ray, planned: dict, progress: bool) -> list[str]:
    """Write the missing shards under a progress bar counting all of this run's scenes; returns
    the ids of tunnelled scenes."""
    total = sum(t.count for t in mine)
    bar = tqdm(total=total, initial=total - sum(t.count for t in todo),
               unit="scene", desc="toss", disable=not progress, file=sys.stderr)
    tunnelled: list[str] = []
    for _, n, bad in _shard_results(todo, cfg, seed, out, workers, ray, planned):
        bar.update(n)
        tunnelled += bad
    bar.close()
    return tunnelled


def _warn_tunnelled(tunnelled: list[str]) -> None:
    if tunnelled:
        # Kept, not dropped, so the dataset stays a function of the seed; inspect lists them.
        print(f"warning: {len(tunnelled)} scene(s) sank through the floor (objects too fast for "
              f"physics.rate; set physics.ccd=true or raise the rate): {', '.join(sorted(tunnelled)[:10])}",
              file=sys.stderr)


def generate(cfg: dict, seed: int, counts: dict[str, int], out: str | Path, workers: int = 1,
             per_shard: int = 50, resume: bool = False, overwrite: bool = False, progress: bool = True,
             backend: str = "process", shard_index: int | None = None, num_shards: int | None = None,
             ray_address: str | None = None) -> dict:
    """Generate a dataset into `out`, or, with `num_shards`, the part `shard_index` of it: the
    shards whose position in the plan (train, then valid, then test shards, each in order)
    modulo num_shards is shard_index. Returns the metadata written last; its `complete` is
    false when other parts are still missing."""
    out = Path(out)
    _check_arguments(counts, workers, per_shard, backend, ray_address)
    sharded = _check_sharding(shard_index, num_shards, overwrite)
    check_floor_covers(cfg)
    tasks = plan(counts, per_shard)
    meta = metadata(cfg, seed, counts, tasks, complete=False)
    mine = [t for k, t in enumerate(tasks) if not sharded or k % num_shards == shard_index]
    check_output(out, meta, sharded, resume, overwrite)     # fails fast, before a cluster is asked
    if backend == "ray":
        from .ray_backend import ray_cluster
    with (ray_cluster(workers, ray_address) if backend == "ray" else nullcontext()) as ray:
        try:
            with claim(out, shared=sharded):
                # A part skips its shards already written (and verified), so a requeued array
                # task redoes only what is missing; a whole run does so only with --resume.
                todo = start_output(out, meta, mine, sharded, resume, overwrite)
                tunnelled = _make_shards(mine, todo, cfg, seed, out, workers, ray, plan_of(meta), progress)
                _warn_tunnelled(tunnelled)
                return finalise(out, meta, tasks)
        except Busy:
            raise busy_error(out, meta, sharded) from None
