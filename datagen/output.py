"""The output folder a `datagen toss` writes: who may write it and when (the claim and the plan
lock), the plan it records in metadata.json, and the checks that a kept shard is the one written.

Two runs that each checked an output folder before either wrote to it would both find it free
and write one mixed dataset that its metadata calls one seed. So every `datagen toss` claims
its --out with flock before it looks at what is there, and holds the claim until it ends:

- a whole run claims the folder exclusively: a second run, whole or part, is refused at once;
- the parts of a sharded generation (--num-shards) share the claim with each other, and take
  the plan lock (exclusive, held for milliseconds) to compare or write the plan, to record a
  shard and rename it into place, and to finalise the metadata.

flock rather than O_EXCL lock files: the kernel drops a lock when its holder dies (kill -9,
a node lost), so no stale lock ever has to be cleaned by hand. The two lock files are removed
by the last holder; a process that locked a file which was removed meanwhile sees its inode
differ from the path's and locks the new file instead.

metadata.json is written first with `complete: false` (the plan), records each shard's sha256
under `written` just before the shard is renamed into place, and is rewritten with `complete:
true` once every shard of the plan is there and is the shard recorded.
"""
from __future__ import annotations

import errno
import fcntl
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from plumbing import atomic_file, DataError, file_sha256
from .shards import (METADATA_FILE, SHARED, SPLITS, clear_dataset, dataset_files, own_temporary, shard_name,
                     temporary_target, write_metadata, write_shard_image)

CLAIM_FILE = ".datagen-toss.claim"
LOCK_FILE = ".datagen-toss.lock"
LOCK_FILES = (CLAIM_FILE, LOCK_FILE)

# fds held by this process; a forked pool worker closes its copies so that the claim dies with
# the process that took it, not with the last of its workers.
_held: set[int] = set()


def _close_in_child() -> None:
    for fd in list(_held):
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


os.register_at_fork(after_in_child=_close_in_child)


@contextmanager
def new_dataset(out: Path, overwrite: bool) -> Iterator[list[Path]]:
    """A dataset folder an importer fills (cleared with `overwrite`), listing what it writes in the
    yielded list: on any failure those files go, and the folder if this made it and it is empty."""
    created, written = not out.exists(), []
    try:
        out.mkdir(parents=True, exist_ok=True)
        if overwrite:
            clear_dataset(out)
        yield written
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


class Busy(Exception):
    """The folder is claimed by another run."""


def _lock(path: Path, how: int) -> int:
    """An fd of `path` locked with flock `how`; raises Busy (LOCK_NB) if another holds it."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, how)
        except BlockingIOError:
            os.close(fd)
            raise Busy(str(path)) from None
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.ENOSYS, errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
                path.unlink(missing_ok=True)  # the lock file is ours alone: no run can hold it
                # a file system without flock (Lustre without -o flock, some FUSE and NFS mounts):
                # without it two runs could mix one dataset, so say so rather than write unguarded
                raise DataError(f"cannot lock {path}: its file system does not support flock "
                                f"({os.strerror(e.errno)}); write the dataset to a local or flock-capable "
                                "file system") from None
            raise
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # locked a file its last holder had just removed: lock the one there now


def _remove_if_last(out: Path, fd: int) -> None:
    """Remove the lock files if no other process holds the claim (then none can be waiting on it)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return
    for name in (LOCK_FILE, CLAIM_FILE):    # the claim last: holding it guards the other's removal
        try:
            (out / name).unlink()
        except OSError:
            pass


@contextmanager
def claim(out: str | Path, shared: bool) -> Iterator[bool]:
    """Hold the claim of folder `out` (made if missing) for the block: exclusive for a whole
    run, shared among the parts of a sharded one. Raises Busy if another run holds it in a
    mode that excludes this one. Yields whether this call made the folder, and removes it on
    the way out if it made it and left it empty."""
    out = Path(out)
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        fd = _lock(out / CLAIM_FILE, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except Busy:
        _rmdir_if_empty(out, made)
        raise
    _held.add(fd)
    try:
        yield made
    finally:
        _remove_if_last(out, fd)
        _held.discard(fd)
        os.close(fd)
        _rmdir_if_empty(out, made)


def _rmdir_if_empty(out: Path, made: bool) -> None:
    if made:
        try:
            out.rmdir()  # fails, as meant, if anything (another run's claim) is in it
        except OSError:
            pass


@contextmanager
def plan_lock(out: str | Path, timeout: float = 600.0) -> Iterator[None]:
    """The plan lock of `out`, held for the block. Its holders keep it for milliseconds (a
    shard's hash at most), so a wait of `timeout` seconds means a hung holder: TimeoutError."""
    path = Path(out) / LOCK_FILE
    deadline = time.monotonic() + timeout
    while True:
        try:
            fd = _lock(path, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except Busy:
            if time.monotonic() > deadline:
                raise TimeoutError(f"the plan lock {path} has been held for {timeout:g} s") from None
            time.sleep(0.01)
    _held.add(fd)
    try:
        yield
    finally:
        _held.discard(fd)
        os.close(fd)


# The plan, fixed before any shard is simulated so that a resumed run or another part can be
# checked against it: the shards in order, and the metadata keys that decide what they hold.


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


PLAN_KEYS = ("config", "seed", "splits")


# The incomplete metadata's table of shards written so far and their sha256: what --resume and
# the finalising run verify kept shards against. Gone from the complete metadata (its
# `checksums` take over).
WRITTEN = "written"


def plan_of(meta: dict) -> dict:
    return {k: meta[k] for k in PLAN_KEYS}


def plan_difference(old, planned: dict) -> str | None:
    """The first plan key in which `old` (a metadata.json) differs from `planned`, or None."""
    for key in PLAN_KEYS:
        if not isinstance(old, dict) or old.get(key) != planned[key]:
            return key
    return None


def read_metadata(out: Path, what: str) -> dict:
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


def recorded_checksums(old: dict) -> dict[str, str]:
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
        old = read_metadata(out, f"write {name}")
        key = plan_difference(old, planned)
        if key:
            raise DataError(f"cannot write {name} into {out}: its {key} changed since this run started "
                            "(another run replaced the plan)")
        old.setdefault(WRITTEN, {})[name] = digest
        _write_json(out, old)
        write_shard_image(out / name, image)


def same_plan(out: Path, meta: dict, what: str) -> dict:
    """The metadata in `out`, refused in one line if its plan is not `meta`'s."""
    old = read_metadata(out, what)
    key = plan_difference(old, plan_of(meta))
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
            same_plan(out, meta, "add shards to")
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
            same_plan(out, meta, "resume")
    elif resume:
        raise DataError(f"cannot resume: {out} does not exist" if not out.exists() else
                        f"cannot resume: {out} has no {METADATA_FILE}")


def to_make(out: Path, tasks: list[ShardTask], recorded: dict[str, str], what: str) -> list[ShardTask]:
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


def remove_temporaries(out: Path, names: list[str], whole_run: bool) -> None:
    """Remove the temporary files of `names` and, in a whole run (an exclusive claim), all of ours."""
    for p in out.glob(".*.tmp"):
        if temporary_target(p.name) in names or (whole_run and own_temporary(p.name)):
            p.unlink(missing_ok=True)


@contextmanager
def temporaries_removed_on_failure(out: Path, names: list[str], whole_run: bool) -> Iterator[None]:
    """If the block writing the shards `names` fails or is stopped, the temporary files its stopped
    workers left are removed (the plan is written under the plan lock only: one seen there is theirs)."""
    try:
        yield
    except BaseException:
        with plan_lock(out):
            remove_temporaries(out, [*names, METADATA_FILE], whole_run)
        raise


def prepare_output(out: Path, meta: dict, tasks: list[ShardTask], resume: bool, overwrite: bool) -> list[ShardTask]:
    """Make the claimed folder of a whole run ready and write its plan; returns the shards to make.
    --resume verifies the shards it keeps before anything is rewritten."""
    check_output(out, meta, False, resume, overwrite)
    written: dict[str, str] = {}
    if overwrite:
        clear_dataset(out)  # only the tool's own files: a user's notes in the folder stay
        todo = tasks
    elif resume and _foreign(out):
        old = same_plan(out, meta, "resume")
        recorded = recorded_checksums(old)
        todo = to_make(out, tasks, recorded, "resume")
        remove_temporaries(out, [], whole_run=True)
        if not todo and old.get("complete") is True:
            return []                       # verified and complete: nothing to rewrite
        written = {t.name: recorded[t.name] for t in tasks if t not in todo}
    else:
        todo = tasks
    write_metadata(out, {**meta, WRITTEN: written})
    return todo


def start_output(out: Path, meta: dict, mine: list[ShardTask], sharded: bool, resume: bool,
                  overwrite: bool) -> list[ShardTask]:
    """Make the claimed folder ready and write the incomplete metadata (a shared folder's only if
    none is there); returns the shards of `mine` still to make."""
    with plan_lock(out):
        if sharded:
            from .shared_output import prepare_shared_output
            return prepare_shared_output(out, meta, mine)
        return prepare_output(out, meta, mine, resume, overwrite)


def finalise(out: Path, meta: dict, tasks: list[ShardTask]) -> dict:
    """The complete metadata, written once every shard of the plan is there and is the shard
    recorded when it was written; else the plan, marked incomplete. Never hashes over a change:
    a shard changed since it was written is refused by name, and metadata.json stays as it was."""
    with plan_lock(out):
        old = same_plan(out, meta, "finish")
        # Shards appear only complete (temporary file, then rename), so existing means written.
        if any(not (out / t.name).exists() for t in tasks):
            return {**old, "splits": meta["splits"], "complete": False}   # the plan's order of splits
        recorded = recorded_checksums(old)
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
