"""What datagen and gns share and neither owns: the one-line error classes of bad input, safe
writes and checks on outputs, and the TOML presets with their value rules. One module, not a
package: each part is a few dozen lines and every command imports all four.

Errors: each message is one line for a user, and both command lines turn them into
`error: ...` and exit status 2.

Safe writes: a file or folder is written under a temporary name and renamed when complete,
so a crash or a full disk never leaves half of it under its final name (every writer of datasets,
checkpoints, results and figures goes through `atomic_file` or `atomic_folder`); and checks on
where a command will write, made before its work, so that an output that cannot be written,
that would land on the input or replace someone else's files fails in one line instead of after
a long job.

Presets: the TOML presets both tools read (configs/, shipped as the package rigid_gns_configs)
and the rules every config value follows: --set values read as TOML reads them, and one typing
rule.

Provenance: where a dataset or a training run came from (library versions, the code's commit,
the project's version, the dataset fingerprint), recorded in every output.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import tempfile
import tomllib
from contextlib import contextmanager
from functools import lru_cache
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Iterator


# --- errors

class ConfigError(ValueError):
    """A configuration key or value that cannot be used."""


class DataError(Exception):
    """A dataset, shard or output path that does not follow the format or cannot be used."""


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Inside, SIGTERM raises KeyboardInterrupt (the message "SIGTERM") as Ctrl-C does, so that a
    command stopped either way cleans up and says so alike; outside a main thread, nothing."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def leave_signals_to_parent() -> None:
    """For a pool worker (its initializer): SIGTERM kills it at once and Ctrl-C is left to the
    parent, which stops the pool. A forked worker would otherwise keep sigterm_as_interrupt's
    handler: stopping the pool, even at a normal end, raised inside the pool's own queue locks,
    printed a traceback per worker and could leave the parent waiting on a lock a dead one held."""
    import signal
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# --- safe writes and output checks

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


# --- TOML presets and config values

DEFAULT_PRESET = "movi_a"   # the preset that marks a configs/ folder (datagen's scene defaults)


def config_dir() -> Path:
    """The presets (TOML): the checkout's configs/ folder, or, installed from a wheel, the same
    files shipped as the package `rigid_gns_configs` (pyproject.toml maps configs/ to it)."""
    checkout = Path(__file__).resolve().parent / "configs"
    if (checkout / f"{DEFAULT_PRESET}.toml").is_file():
        return checkout
    from importlib.resources import files
    return Path(str(files("rigid_gns_configs")))


def preset_names() -> list[str]:
    return sorted(p.stem for p in config_dir().glob("*.toml"))


def config_path(path: str | Path) -> Path:
    """A TOML file, or a preset's name (gns_cpu, movi_a) looked up among the shipped presets;
    a path into a checkout's configs/ that is not there (installed package) falls back to the
    preset of that name."""
    p = Path(path)
    if p.is_file():
        return p
    if p.suffix in ("", ".toml") and (config_dir() / f"{p.stem}.toml").is_file() and (
            p.parent == Path(".") or p.parent.name == "configs"):
        return config_dir() / f"{p.stem}.toml"
    raise ConfigError(f"config file not found: {path} (presets: {', '.join(preset_names())})")


def load_toml(path: str | Path) -> dict:
    path = config_path(path)
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML ({e})") from None


def typed_value(key: str, value, default, where: str = ""):
    """value checked against the type of the default's (the preset's or the dataclass's): a
    string where a boolean belongs ("no" from a shell) must not be taken as true. Ints are
    accepted for floats. The one typing rule of datagen's and gns's configs."""
    expected = type(default)
    if expected is bool:
        ok = isinstance(value, bool)
    elif expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif expected is int:  # 12.0 from a float flag (--frame-rate) is the whole number 12
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif expected is list:
        ok = isinstance(value, list) and (not default or all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
            == all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in default))
    else:
        ok = isinstance(value, expected)
    if not ok:
        want = {bool: "true or false", float: "a number", int: "a whole number", list: "a list like the preset's",
                str: "a string"}.get(expected, expected.__name__)
        raise ConfigError(f"config key {key!r}{' ' + where if where else ''} must be {want}, got {value!r}")
    return value


def parse_value(text: str):
    """A --set value as TOML would read it (numbers, booleans, lists, quoted or bare strings);
    True/FALSE are booleans too, as a shell user would write them."""
    if text.strip().lower() in ("true", "false"):
        return text.strip().lower() == "true"
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


# --- provenance

# Where a dataset or a training run came from: library versions, the code's git commit, and
# the dataset fingerprint (docs/data_format.md, "Provenance and fingerprint").
#
# Kept out of the shards on purpose: shards stay byte-identical for the same seed and config on
# any machine, so versions and commits live in metadata.json, checkpoints and JSON outputs only.


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
    if not top or not _git(["ls-files", "--error-unmatch", Path(__file__).name], here):
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
