"""Analytic baselines for the real cube tosses: PyBullet and MuJoCo, each with its contact
parameters identified on the GNS's training tosses (docs/results.md).

    baselines.toss          the toss protocol every engine follows (given frames, start state, score)
    baselines.identify      identification of an engine's parameters on training tosses
    baselines.pybullet      the PyBullet engine
    baselines.mujoco        the MuJoCo engine (the optional [mujoco] extra)
    baselines.engine_tosses synthetic tosses simulated by an identified engine
"""
from __future__ import annotations

from typing import Callable


def baseline_engine(name: str) -> tuple[type, Callable, Callable]:
    """(parameter class, simulate_toss, fit_parameters) of an engine: "pybullet" or "mujoco"."""
    if name == "pybullet":
        from baselines import pybullet
        return pybullet.BaselineParams, pybullet.simulate_toss, pybullet.fit_parameters
    if name == "mujoco":
        from baselines import mujoco  # imports the mujoco package itself only when it simulates
        return mujoco.MujocoParams, mujoco.simulate_toss, mujoco.fit_parameters
    raise ValueError(f"unknown baseline engine {name!r}: pybullet or mujoco")
