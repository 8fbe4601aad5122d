"""Plan a dataset as shards, simulate them on worker processes or a Ray cluster, write shards
and metadata.

A shard is the unit of work and of writing: its content depends only on (config, seed,
split, shard index), never on the worker count, the backend or how the shards are divided
among runs. `metadata.json` is written first with `complete: false` (so `--resume` knows the
plan), records each shard's sha256 under `written` just before the shard is renamed into place,
and is rewritten with `complete: true`, checksums and the fingerprint once every shard of the
plan is there and is the shard recorded. With `--shard-index I --num-shards K` several runs (a
Slurm array) share one folder: each writes only its shards, and whichever run sees the last
shard present finalises the metadata. Every run claims the folder first (datagen/claim.py), so
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
from .scenes import sample_scene
from .shapes import get_shape
from .inspect import floor_violations
from .claim import LOCK_FILES, Busy, claim, plan_lock
from .provenance import file_sha256
from .shards import (METADATA_FILE, SHARED, SPLITS, clear_dataset, dataset_files, shard_image,
                     shard_name, write_error, write_metadata, write_shard_image)
from .simulate import FLOOR_HALF_WIDTH, check_floor_covers, off_floor, simulate, steps_per_frame
from plumbing import atomic_file, DataError


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


PLAN_KEYS = ("config", "seed", "splits")
# The incomplete metadata's table of shards written so far and their sha256: what --resume and
# the finalising run verify kept shards against. Gone from the complete metadata (its
# `checksums` take over).
WRITTEN = "written"


def _plan_of(meta: dict) -> dict:
    return {k: meta[k] for k in PLAN_KEYS}


def _plan_difference(old, planned: dict) -> str | None:
    """The first plan key in which `old` (a metadata.json) differs from `planned`, or None."""
    for key in PLAN_KEYS:
        if not isinstance(old, dict) or old.get(key) != planned[key]:
            return key
    return None


def _read_metadata(out: Path, what: str) -> dict:
    import json
    path = out / METADATA_FILE
    try:
        old = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"cannot {what}: {path} is gone (another run cleared {out})") from None
    except (OSError, ValueError) as e:
        raise DataError(f"cannot {what}: {path} is unreadable ({e})") from None
    if not isinstance(old, dict):
        raise DataError(f"cannot {what}: {path} is not a JSON object")
    return old


def _write_json(out: Path, meta: dict) -> None:
    import json
    with atomic_file(out / METADATA_FILE, mode=SHARED) as tmp:
        tmp.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def _recorded(old: dict) -> dict[str, str]:
    """sha256 by shard name, as the metadata recorded them when the shards were written."""
    rec = {}
    for key in ("checksums", WRITTEN):
        if isinstance(old.get(key), dict):
            rec.update(old[key])
    return rec


def commit_shard(out: Path, planned: dict, name: str, image: bytes) -> None:
    """Record a shard's checksum in the plan, then rename it into place, both under the plan
    lock and only if the plan in the folder is still this run's: a run whose folder was taken
    over by another plan stops instead of adding its shard to the other dataset. Recorded
    before renamed, so every shard present has its checksum recorded."""
    import hashlib
    digest = hashlib.sha256(image).hexdigest()
    with plan_lock(out):
        old = _read_metadata(out, f"write {name}")
        key = _plan_difference(old, planned)
        if key:
            raise DataError(f"cannot write {name} into {out}: its {key} changed since this run started "
                            "(another run replaced the plan)")
        old.setdefault(WRITTEN, {})[name] = digest
        _write_json(out, old)
        write_shard_image(out / name, image)


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


def _same_plan(out: Path, meta: dict, what: str) -> dict:
    """The metadata in `out`, refused in one line if its plan is not `meta`'s."""
    old = _read_metadata(out, what)
    key = _plan_difference(old, _plan_of(meta))
    if key:
        raise DataError(f"cannot {what} {out}: its {key} differs from this command's")
    return old


def _foreign(out: Path) -> list[Path]:
    """What a folder holds besides the claim's lock files."""
    return [p for p in out.iterdir() if p.name not in LOCK_FILES] if out.is_dir() else []


def check_output(out: Path, meta: dict, sharded: bool, resume: bool, overwrite: bool) -> None:
    """Refuse, writing nothing, an output folder this run may not write: checked once before
    the work starts (a Ray cluster may take a while to answer) and again under the claim."""
    if out.exists() and not out.is_dir():
        raise DataError(f"output path {out} is a file, not a folder")
    held = _foreign(out)
    if sharded:
        if (out / METADATA_FILE).exists():
            _same_plan(out, meta, "add shards to")
        elif any(p not in dataset_files(out) for p in held):
            raise DataError(f"output folder {out} holds files that are not a dataset's and no {METADATA_FILE}; "
                            "give sharded runs an empty or new folder")
    elif held:
        if not (resume or overwrite):
            raise DataError(f"output folder {out} exists and is not empty; "
                            "use --resume to finish it or --overwrite to replace it")
        if overwrite and not dataset_files(out):
            raise DataError(f"{out} exists and does not look like a dataset; refusing to delete it")
        if resume:
            if not (out / METADATA_FILE).exists():
                raise DataError(f"cannot resume: {out} has no {METADATA_FILE}")
            _same_plan(out, meta, "resume")
    elif resume:
        raise DataError(f"cannot resume: {out} does not exist" if not out.exists() else
                        f"cannot resume: {out} has no {METADATA_FILE}")


def _kept(out: Path, tasks: list[ShardTask], recorded: dict[str, str], what: str) -> list[ShardTask]:
    """The shards of `tasks` still to make: those missing, or present without a recorded
    checksum (written by hand or by an older datagen: made again, never trusted). A present
    shard whose bytes are not the recorded ones is refused: it was changed since it was written."""
    todo = []
    for t in tasks:
        path = out / t.name
        if not path.exists():
            todo.append(t)
        elif t.name not in recorded:
            todo.append(t)
        elif file_sha256(path) != recorded[t.name]:
            raise DataError(f"cannot {what} {out}: {t.name} changed since it was written (its sha256 is not the "
                            "one recorded); move it away to have it made again, or restore it")
    return todo


def prepare_output(out: Path, meta: dict, tasks: list[ShardTask], resume: bool, overwrite: bool) -> list[ShardTask]:
    """Make the claimed folder of a whole run ready and write its plan; returns the shards to make.
    --resume verifies the shards it keeps before anything is rewritten."""
    check_output(out, meta, False, resume, overwrite)
    written: dict[str, str] = {}
    if overwrite:
        clear_dataset(out)  # only the tool's own files: a user's notes in the folder stay
        todo = tasks
    elif resume and _foreign(out):
        old = _same_plan(out, meta, "resume")
        recorded = _recorded(old)
        todo = _kept(out, tasks, recorded, "resume")
        for stale in out.glob(".*.tmp"):    # the claim is exclusive: no other run is writing these
            stale.unlink(missing_ok=True)
        if not todo and old.get("complete") is True:
            return []                       # verified and complete: nothing to rewrite
        written = {t.name: recorded[t.name] for t in tasks if t not in todo}
    else:
        todo = tasks
    write_metadata(out, {**meta, WRITTEN: written})
    return todo


def prepare_shared_output(out: Path, meta: dict, mine: list[ShardTask]) -> list[ShardTask]:
    """The claimed folder of a part of a sharded generation (--num-shards), which other parts
    share: it may be new, empty, hold the same plan, or hold only the tool's files of a part
    that is just starting. Called under the plan lock, so the plan is written once, by the
    first part, and every other part compares its plan with it. Returns this part's shards to make."""
    check_output(out, meta, True, False, False)
    # Only this part's own leftovers: another part's temporary files may be shards being written.
    for task in mine:
        for stale in out.glob(f".{task.name}.*.tmp"):
            stale.unlink(missing_ok=True)
    if not (out / METADATA_FILE).exists():
        write_metadata(out, {**meta, WRITTEN: {}})
        return list(mine)
    old = _same_plan(out, meta, "add shards to")
    recorded = _recorded(old)
    todo = _kept(out, mine, recorded, "add shards to")
    if todo and old.get("complete") is True:
        # A finished dataset that lost a shard of this part: incomplete again until it is back.
        kept = {name: d for name, d in recorded.items() if (out / name).exists()}
        write_metadata(out, {**meta, WRITTEN: kept})
    return todo


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


def _start_output(out: Path, meta: dict, mine: list[ShardTask], sharded: bool, resume: bool,
                  overwrite: bool) -> list[ShardTask]:
    """Make the claimed folder ready and write the incomplete metadata (a shared folder's only if
    none is there); returns the shards of `mine` still to make."""
    with plan_lock(out):
        if sharded:
            return prepare_shared_output(out, meta, mine)
        return prepare_output(out, meta, mine, resume, overwrite)


def _busy(out: Path, meta: dict, sharded: bool) -> DataError:
    """One line for a folder another run has claimed, naming how its plan differs when it has
    written one (it does so right after claiming: a moment's wait)."""
    import time
    planned, old = _plan_of(meta), None
    deadline = time.monotonic() + 3.0
    # Read without the plan lock: metadata.json is only ever replaced whole, and taking the lock
    # here could leave its file behind in a folder whose holder has just cleaned up.
    while old is None and time.monotonic() < deadline:
        try:
            old = _read_metadata(out, "read the plan") if (out / METADATA_FILE).exists() else None
        except DataError:
            break
        if old is None:
            time.sleep(0.05)
    who = "a whole `datagen toss` run" if sharded else "another `datagen toss`"
    key = _plan_difference(old, planned) if old is not None else None
    if key:
        return DataError(f"cannot write {out}: {who} is writing a dataset there whose {key} differs from this command's")
    return DataError(f"cannot write {out}: {who} is writing it now; wait for it to end "
                     "(then --resume finishes the same plan)")


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
        # h5py, a fifth of a small run. Safe because the parent holds no PyBullet client.
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
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


def _finalise(out: Path, meta: dict, tasks: list[ShardTask]) -> dict:
    """The complete metadata, written once every shard of the plan is there and is the shard
    recorded when it was written; else the plan, marked incomplete. Never hashes over a change:
    a shard changed since it was written is refused by name, and metadata.json stays as it was."""
    with plan_lock(out):
        old = _same_plan(out, meta, "finish")
        # Shards appear only complete (temporary file, then rename), so existing means written.
        if any(not (out / t.name).exists() for t in tasks):
            return {**old, "splits": meta["splits"], "complete": False}   # the plan's order of splits
        recorded = _recorded(old)
        for t in tasks:
            if t.name not in recorded:
                raise DataError(f"cannot finish {out}: {t.name} is there but no run of this plan recorded writing "
                                "it; move it away and rerun to have it made")
            if file_sha256(out / t.name) != recorded[t.name]:
                raise DataError(f"cannot finish {out}: {t.name} changed since it was written (its sha256 is not "
                                "the one recorded); move it away to have it made again, or restore it")
        if old.get("complete") is True:
            return {**old, "splits": meta["splits"]}    # verified, nothing to rewrite
        return write_metadata(out, {**meta, "complete": True})


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
                todo = _start_output(out, meta, mine, sharded, resume, overwrite)
                tunnelled = _make_shards(mine, todo, cfg, seed, out, workers, ray, _plan_of(meta), progress)
                _warn_tunnelled(tunnelled)
                return _finalise(out, meta, tasks)
        except Busy:
            raise _busy(out, meta, sharded) from None
