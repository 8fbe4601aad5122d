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
        raise DataError(f"cannot write to the {what} {path}: {existing} is not writable ({e.strerror or e})") from None
    return path


def overlapping(a: str | Path, b: str | Path) -> bool:
    """Whether folders a and b are the same or one lies inside the other (after symlinks)."""
    a, b = Path(a).resolve(), Path(b).resolve()
    return a == b or a in b.parents or b in a.parents


def check_json_output(path: str | Path, marker: str, what: str) -> Path:
    """A JSON output file that may be replaced: new, or an earlier output of the same command
    (a dict holding key `marker`), so a mistyped path never overwrites someone else's file
    (a dataset's metadata.json, say)."""
    import json
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a folder; give a file name such as {path / 'results.json'}")
    if path.exists():
        try:
            ours = marker in json.loads(path.read_text())
        except (OSError, ValueError, TypeError):
            ours = False
        if not ours:
            raise DataError(f"{path} exists and is not a {what} output; refusing to replace it")
    return check_writable(path.parent, "--json folder")
