"""Toss data generation (PyBullet) and the shard format the GNS reads."""

__version__ = "0.1.0"
