"""Where a dataset or a training run came from: library versions, the code's git commit, and
the dataset fingerprint (docs/data_format.md, "Provenance and fingerprint").

Kept out of the shards on purpose: shards stay byte-identical for the same seed and config on
any machine, so versions and commits live in metadata.json, checkpoints and JSON outputs only.
"""
from __future__ import annotations

import hashlib
import json
import platform
import subprocess
from functools import lru_cache
from importlib import metadata as importlib_metadata
from pathlib import Path
import importlib.metadata
import tomllib

# The libraries whose versions can change a dataset or a trained model (distribution names).
LIBRARIES = ("rigid-gns", "torch", "numpy", "pybullet", "h5py", "trimesh", "scipy")

# metadata.json keys that say how or when a dataset was made, not what it holds: left out of
# the fingerprint so the same data made by another version, machine or path fingerprint alike.
NOT_FINGERPRINTED = ("complete", "provenance", "checksums", "fingerprint", "generator_version", "rollout")


def versions() -> dict[str, str | None]:
    """Python and library versions, read from the installed distributions (nothing is imported,
    so datagen does not pay for importing torch); a library that is not installed is None."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = None
    return out


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        r = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):  # no git, or a hung one
        return None
    return r.stdout.strip() if r.returncode == 0 else None


@lru_cache(maxsize=1)
def code_version() -> dict | None:
    """{"commit": sha, "dirty": bool} of the checkout this package runs from, or None when it
    does not run from a git checkout (an installed wheel). A package directory that lies inside
    some repository but is not tracked by it (a virtualenv inside a checkout) is not a checkout:
    that repository's commit would describe other code."""
    here = Path(__file__).resolve().parent
    top = _git(["rev-parse", "--show-toplevel"], here)
    if not top or not _git(["ls-files", "--error-unmatch", "__init__.py"], here):
        return None
    commit = _git(["rev-parse", "HEAD"], here)
    if not commit:
        return None
    # Untracked files are ignored: data, runs and virtualenvs in the checkout do not change code.
    status = _git(["status", "--porcelain", "--untracked-files=no"], here)
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def provenance() -> dict:
    """Versions and code commit: what every dataset and run records."""
    return {"versions": versions(), "code": code_version()}


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint(meta: dict, checksums: dict[str, str]) -> str:
    """sha256 of the canonical JSON of the metadata's data keys and every shard's sha256.

    Shards are byte-identical for the same seed and config (whatever the worker count, backend
    or sharding), so the same seed and config give the same fingerprint."""
    body = {"metadata": {k: v for k, v in meta.items() if k not in NOT_FINGERPRINTED},
            "shards": dict(sorted(checksums.items()))}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


DISTRIBUTION = "rigid-gns"
PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"


def version() -> str:
    # In a source checkout its pyproject.toml is the truth: an install's metadata keeps the version
    # it was installed at (an editable install too) until it is reinstalled.
    try:
        with open(PYPROJECT, "rb") as f:
            project = tomllib.load(f).get("project", {})
        if project.get("name") == DISTRIBUTION and project.get("version"):
            return str(project["version"])
    except (OSError, tomllib.TOMLDecodeError):
        pass
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def version_line() -> str:
    return f"{DISTRIBUTION} {version()}"
