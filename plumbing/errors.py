"""The error classes of bad input that both tools raise: each message is one line for a user, and
both command lines turn them into `error: ...` and exit status 2."""
from __future__ import annotations


class ConfigError(ValueError):
    """A configuration key or value that cannot be used."""


class DataError(Exception):
    """A dataset, shard or output path that does not follow the format or cannot be used."""
