"""Plan a dataset as shards, simulate them on worker processes or a Ray cluster, write shards
and metadata.

A shard is the unit of work and of writing: its content depends only on (config, seed,
split, shard index), never on the worker count, the backend or how the shards are divided
among runs. `metadata.json` is written first with `complete: false` (so `--resume` knows the
plan) and rewritten with `complete: true`, checksums and the fingerprint once every shard of
the plan exists. With `--shard-index I --num-shards K` several runs (a Slurm array) share one
folder: each writes only its shards, and whichever run sees the last shard present finalises
the metadata (idempotent: two runs finishing together write the same file, atomically).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import __version__
from .scenes import sample_scene
from .shapes import get_shape
from .inspect import floor_violations
from .shards import (METADATA_FILE, SPLITS, clear_dataset, dataset_files, read_shard, shard_image, shard_name,
                     write_error, write_metadata, write_shard_image)
from .simulate import simulate, steps_per_frame
from plumbing.errors import ConfigError, DataError
from plumbing.files import check_output_folder


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
    bad = [sc.attrs["scene_id"] for sc in scenes if floor and floor_violations(sc, meshes, 0.0, dt)]
    image = shard_image(scenes, meshes, {"split": task.split, "shard": task.shard, "seed": seed,
                                         "first_scene": task.first}, task.name)
    return image, bad


def run_task(args) -> tuple[str, int, list[str]]:
    """Simulate and write one shard. Returns its name, scene count and ids of tunnelled scenes."""
    task, cfg, seed, out = args
    try:
        image, bad = build_task(task, cfg, seed)
    except OSError as e:  # HDF5 failing to build the file in memory: one line, as a failed write
        raise write_error(Path(out) / task.name, e) from None
    write_shard_image(Path(out) / task.name, image)
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


def _same_plan(out: Path, meta: dict, what: str) -> None:
    import json
    path = out / METADATA_FILE
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(f"cannot {what}: {path} is unreadable ({e})") from None
    for key in ("config", "seed", "splits"):
        if not isinstance(old, dict) or old.get(key) != meta[key]:
            raise DataError(f"cannot {what} {out}: its {key} differs from this command's")


def prepare_output(out: Path, meta: dict, resume: bool, overwrite: bool) -> None:
    """Refuse to mix datasets: an existing folder needs --resume (same plan) or --overwrite."""
    if check_output_folder(out, overwrite or resume, "use --resume to finish it or --overwrite to replace it"):
        if overwrite:
            if not dataset_files(out):
                raise DataError(f"{out} exists and does not look like a dataset; refusing to delete it")
            clear_dataset(out)  # only the tool's own files: a user's notes in the folder stay
        else:
            if not (out / METADATA_FILE).exists():
                raise DataError(f"cannot resume: {out} has no {METADATA_FILE}")
            _same_plan(out, meta, "resume")
            for stale in out.glob(".*.tmp"):
                stale.unlink()
    elif resume:
        raise DataError(f"cannot resume: {out} does not exist")
    out.mkdir(parents=True, exist_ok=True)


def prepare_shared_output(out: Path, meta: dict, mine: list[ShardTask]) -> None:
    """The folder of a run of a sharded generation (--num-shards), which other runs share: it
    may be missing, empty, hold the same plan, or hold only the tool's files of a run that is
    just starting (no metadata.json yet). The plan is written only where none is, so a late run
    never marks a finished dataset incomplete again."""
    if (out / METADATA_FILE).exists():
        _same_plan(out, meta, "add shards to")
    elif out.exists() and any(p not in dataset_files(out) for p in out.iterdir()):
        raise DataError(f"output folder {out} holds files that are not a dataset's and no {METADATA_FILE}; "
                        "give sharded runs an empty or new folder")
    out.mkdir(parents=True, exist_ok=True)
    # Only this run's own leftovers: another run's temporary files may be shards being written.
    for task in mine:
        for stale in out.glob(f".{task.name}.*.tmp"):
            stale.unlink(missing_ok=True)
    if not (out / METADATA_FILE).exists():
        write_metadata(out, meta)


def require_ray():
    """The ray module, or one line naming the extra (checked before anything is written)."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--backend ray needs Ray: pip install 'rigid-gns[ray]'") from None
    return ray


def _ray_tasks(jobs: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int, address: str | None):
    """Run shards as Ray tasks, yielding (name, count, tunnelled ids) as each is written.

    A task returns its shard's bytes and the driver writes them, so the cluster's nodes need no
    shared file system with --out; with no address (and no RAY_ADDRESS) a local cluster of
    `workers` CPUs is started here and stopped afterwards."""
    ray = require_ray()
    import logging
    address = address or os.environ.get("RAY_ADDRESS") or None
    started = not ray.is_initialized()
    if started:
        try:
            if address:
                ray.init(address=address, logging_level=logging.WARNING)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING)
        except Exception as e:  # ray raises ConnectionError, RuntimeError, ValueError... for a bad address
            where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise DataError(f"cannot start or reach {where}: {first}") from None
    try:
        remote = ray.remote(num_cpus=1)(build_task)  # retried if a node dies: a shard is a pure function of its task
        cfg_ref = ray.put(cfg)
        pending = {remote.remote(t, cfg_ref, seed): t for t in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            task = pending.pop(done[0])
            try:
                image, bad = ray.get(done[0])
            except ray.exceptions.RayTaskError as e:
                cause = getattr(e, "cause", None)
                if isinstance(cause, (DataError, ConfigError)):
                    raise cause from None
                if isinstance(cause, OSError):
                    raise write_error(out / task.name, cause) from None
                raise DataError(f"ray task for {task.name} failed: {type(cause or e).__name__}: "
                                f"{str(cause or e).splitlines()[0] if str(cause or e) else ''}") from None
            write_shard_image(out / task.name, image)
            yield task.name, task.count, bad
    finally:
        if started:
            ray.shutdown()


BACKENDS = ("process", "ray")


def _check_arguments(counts: dict[str, int], workers: int, per_shard: int, backend: str) -> None:
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
    if backend == "ray":
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


def _start_output(out: Path, meta: dict, mine: list[ShardTask], sharded: bool, resume: bool,
                  overwrite: bool) -> None:
    """Make the folder ready and write the incomplete metadata (a shared folder's only if none is there)."""
    if sharded:
        prepare_shared_output(out, meta, mine)
    else:
        prepare_output(out, meta, resume, overwrite)
        write_metadata(out, meta)


def _shard_results(todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int, backend: str,
                   ray_address: str | None):
    """Write the shards of `todo` on the chosen backend, yielding (name, count, tunnelled ids) for each."""
    jobs = [(t, cfg, seed, str(out)) for t in todo]
    if backend == "ray" and todo:
        yield from _ray_tasks(todo, cfg, seed, out, workers, ray_address)
    elif workers == 1 or len(todo) <= 1:
        for job in jobs:
            yield run_task(job)
    else:
        # fork where the platform has it: a spawned worker pays ~0.5 s re-importing trimesh and
        # h5py, a fifth of a small run. Safe because the parent holds no PyBullet client.
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        with mp.get_context(method).Pool(min(workers, len(todo))) as pool:
            yield from pool.imap_unordered(run_task, jobs)


def _make_shards(mine: list[ShardTask], todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int,
                  backend: str, ray_address: str | None, progress: bool) -> list[str]:
    """Write the missing shards under a progress bar counting all of this run's scenes; returns
    the ids of tunnelled scenes."""
    total = sum(t.count for t in mine)
    bar = tqdm(total=total, initial=total - sum(t.count for t in todo),
               unit="scene", desc="toss", disable=not progress, file=sys.stderr)
    tunnelled: list[str] = []
    for _, n, bad in _shard_results(todo, cfg, seed, out, workers, backend, ray_address):
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


def _finalise(out: Path, meta: dict, tasks: list[ShardTask]) -> dict:
    """The complete metadata, written, once every shard of the plan exists; else `meta` unchanged."""
    # Shards appear only complete (temporary file, then rename), so existing means written.
    if any(not (out / t.name).exists() for t in tasks):
        return meta
    meta["complete"] = True
    return write_metadata(out, meta)


def generate(cfg: dict, seed: int, counts: dict[str, int], out: str | Path, workers: int = 1,
             per_shard: int = 50, resume: bool = False, overwrite: bool = False, progress: bool = True,
             backend: str = "process", shard_index: int | None = None, num_shards: int | None = None,
             ray_address: str | None = None) -> dict:
    """Generate a dataset into `out`, or, with `num_shards`, the part `shard_index` of it: the
    shards whose position in the plan (train, then valid, then test shards, each in order)
    modulo num_shards is shard_index. Returns the metadata written last; its `complete` is
    false when other parts are still missing."""
    out = Path(out)
    _check_arguments(counts, workers, per_shard, backend)
    sharded = _check_sharding(shard_index, num_shards, overwrite)
    tasks = plan(counts, per_shard)
    meta = metadata(cfg, seed, counts, tasks, complete=False)
    mine = [t for k, t in enumerate(tasks) if not sharded or k % num_shards == shard_index]
    _start_output(out, meta, mine, sharded, resume, overwrite)
    # A sharded run skips its shards already written, so a requeued array task redoes only what
    # is missing; a whole run does so only with --resume (without it the folder was empty).
    todo = [t for t in mine if not ((resume or sharded) and _shard_ok(out / t.name, t.count))]
    tunnelled = _make_shards(mine, todo, cfg, seed, out, workers, backend, ray_address, progress)
    _warn_tunnelled(tunnelled)
    return _finalise(out, meta, tasks)
