"""Checks on where a command will write, made before its work: an output that cannot be
written, that would land on the input or replace someone else's files fails in one line
instead of after a long job. datagen's and gns's commands all check through this module."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from datagen.shards import DataError


def check_output_folder(out: str | Path, overwrite: bool, advice: str) -> bool:
    """Refuse an output folder that is a file, or that holds files when `overwrite` is not
    given (`advice` says what to pass instead). Returns whether it holds files: what the caller
    may replace, only its own ones."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"output path {out} is a file, not a folder")
    held = out.is_dir() and any(out.iterdir())
    if held and not overwrite:
        raise DataError(f"output folder {out} exists and is not empty; {advice}")
    return held


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
