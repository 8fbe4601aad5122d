"""Safe writes: a file or folder is written under a temporary name and renamed when complete,
so a crash or a full disk never leaves half of it under its final name (every writer of datasets,
checkpoints, results and figures goes through `atomic_file` or `atomic_folder`); and checks on
where a command will write, made before its work, so that an output that cannot be written,
that would land on the input or replace someone else's files fails in one line instead of after
a long job."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from plumbing.errors import DataError


@contextmanager
def atomic_file(path: str | Path, mode: int | None = None, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary file beside `path` to write; renamed to `path` when the block ends without
    error, deleted otherwise.

    The name is `.<name>.<random><suffix>` in the same folder (a rename across file systems
    would not be atomic); a writer that picks its format from the file ending (matplotlib)
    passes path's own suffix. mkstemp makes owner-only files: `mode` (e.g. 0o644 for files
    meant to be shared) is set before the rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """A temporary folder beside `path` to fill; it replaces `path` (and whatever was there)
    when the block ends without error, and is deleted otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # mkdtemp makes owner-only folders; a dataset is meant to be shared
        if path.exists():
            shutil.rmtree(path)
        tmp.rename(path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


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
