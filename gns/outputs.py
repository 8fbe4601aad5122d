"""Checks on where a command will write, made before its work: an output that cannot be
written, or that would land on the input, fails in one line instead of after a long job."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from datagen.shards import DataError


def check_writable(path: str | Path, what: str = "output folder") -> Path:
    """Check that folder `path` can be created (if missing) and written, creating nothing.

    The probe is a temporary file in the nearest folder that exists, removed at once."""
    path = Path(path)
    existing = path.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "it is a file" if existing == path.absolute() else f"{existing} is a file"
        raise DataError(f"cannot write to the {what} {path}: {where}")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=existing)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise DataError(f"cannot write to the {what} {path}: {e.strerror or e} in {existing}") from None
    return path


def overlapping(a: str | Path, b: str | Path) -> bool:
    """Whether folders a and b are the same or one lies inside the other (after symlinks)."""
    a, b = Path(a).resolve(), Path(b).resolve()
    return a == b or a in b.parents or b in a.parents
