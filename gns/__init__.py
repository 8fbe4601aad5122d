"""Graph Network Simulator for rigid bodies (Allen et al., CoRL 2022): model, training, rollouts, metrics.

From Python: `gns.load(...)` returns a `gns.Model` (gns.api): rollouts from poses and velocities.
"""

_API = ("load", "Model", "State", "Trajectory")


def __getattr__(name: str):
    # lazily, so that `gns --help` and the numpy-only modules do not wait for torch
    if name in _API:
        from gns import api
        return getattr(api, name)
    raise AttributeError(f"module 'gns' has no attribute {name!r}")


__all__ = list(_API)
