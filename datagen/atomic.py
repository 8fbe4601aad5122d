"""Atomic writes: a file or folder is written under a temporary name and renamed when complete,
so a crash or a full disk never leaves half of it under its final name. Every writer of
datasets, checkpoints, results and figures goes through `atomic_file` or `atomic_folder`."""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


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
