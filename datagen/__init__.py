"""Toss data generation (PyBullet) and the shard format the GNS reads."""
from plumbing import version as _version

__version__ = _version()   # the release's (pyproject.toml), recorded in each dataset as generator_version
