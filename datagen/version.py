"""The version `gns --version` and `datagen --version` print: `rigid-gns X.Y.Z`."""
from __future__ import annotations

import importlib.metadata
import tomllib
from pathlib import Path

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
