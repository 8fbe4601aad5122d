"""Who may write a dataset folder, and when: the claim of an output folder and the plan lock.

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
"""
from __future__ import annotations

import errno
import fcntl
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from datagen.shards import DataError

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
