"""Identifying an engine's parameters on training tosses, the same way for every engine.

`identify` is engine-neutral: `fit_gravity` and `fit_floor` measure gravity and the table height
on the tosses, then a seeded Latin hypercube over the searched box and bounded Nelder-Mead from
its best few points minimise the pipeline's own metric (`objective`) on the training tosses.
baselines.pybullet and baselines.mujoco each call it with their simulator and search box.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from baselines.toss import FRAME_RATE, first_frames, half_extent, toss_errors
from datagen.shards import rotation
from datagen.shards import Scene

# One degree of rotation error weighs as much as 0.5% of the width in the fitting objective:
# tuned engines reach ~12% and ~18-25 degrees here, so both terms count about equally.
ROTATION_WEIGHT = 0.5


def lowest_corner_height(scene: Scene) -> np.ndarray:
    """Height of the cube's lowest corner at every frame (T,): p_z - a sum_j |R_zj|."""
    rot = rotation(scene.quaternions[:, 0]).as_matrix()
    return scene.positions[:, 0, 2] - half_extent(scene) * np.abs(rot[:, 2, :]).sum(-1)


def free_flight_frames(scene: Scene, margin: float = 0.05) -> int:
    """Number of leading frames before the lowest corner first comes within `margin` (scene
    units) of the table: the part of the toss that is free flight."""
    near = np.nonzero(lowest_corner_height(scene) < margin)[0]
    return int(near[0]) if len(near) else scene.num_frames


def fit_gravity(scenes: Sequence[Scene], frame_rate: float = FRAME_RATE, margin: float = 0.05,
                min_frames: int = 8) -> float | None:
    """Effective gravity of the data: the median over tosses of -2 x the quadratic coefficient
    of the centre height fitted on each toss's free flight (tosses with at least min_frames
    free frames). None if no toss has enough.

    On the ContactNets tosses this gives ~183.4 half-widths/s^2, 2% below the nominal 187.21
    (9.81 m/s^2 over a 5.24 cm half-width): the length or time calibration is off by that much,
    and a simulator with the nominal value drifts ~1% of the width per 0.1 s of flight.
    """
    values = []
    for sc in scenes:
        k = free_flight_frames(sc, margin)
        if k < min_frames:
            continue
        t = np.arange(k) / frame_rate
        coef = np.polyfit(t, sc.positions[:k, 0, 2], 2)
        values.append(-2.0 * coef[0])
    return float(np.median(values)) if values else None


def fit_floor(scenes: Sequence[Scene], frame_rate: float = FRAME_RATE, max_speed: float = 0.1) -> float | None:
    """Height of the table as the data see it: the median over tosses that end at rest (centre
    slower than max_speed scene units/s over their last 4 frames) of the final centre height
    minus the half-width. None if no toss ends at rest.

    The ContactNets cube rests at z ~ 0.978, not 1 (README: a motion-capture offset), so this
    gives ~ -0.022; a simulator with the table at 0 carries that 1.1% of the width as error on
    every resting frame.
    """
    values = []
    for sc in scenes:
        if sc.num_frames < 5:
            continue
        speed = np.linalg.norm(sc.positions[-1, 0] - sc.positions[-5, 0]) * frame_rate / 4
        if speed < max_speed:
            values.append(sc.positions[-1, 0, 2] - half_extent(sc))
    return float(np.median(values)) if values else None


def objective(params, scenes: Sequence[Scene], frame_rate: float = FRAME_RATE,
              rotation_weight: float = ROTATION_WEIGHT, simulate: Callable | None = None,
              horizon: int | None = None) -> float:
    """Mean over tosses of position error % + rotation_weight x rotation error in degrees, over
    each toss's first `horizon` frames (all frames if None). `simulate(scene, params,
    frame_rate)` is the engine (default: baselines.pybullet's)."""
    if simulate is None:
        from baselines.pybullet import simulate_toss as simulate
    total = 0.0
    for sc in scenes:
        sc = first_frames(sc, horizon)
        pos, rot = toss_errors(simulate(sc, params, frame_rate), sc)
        total += pos + rotation_weight * rot
    return total / len(scenes)


def _field(name: str) -> str:
    return name[len("log10_"):] if name.startswith("log10_") else name


def params_from_unit(u: np.ndarray, names: Sequence[str], base, bounds) -> object:
    """base with the searched fields set from a point u of the unit cube (one entry per name)."""
    box = {n: (lo, hi) for n, lo, hi in bounds}
    values = {}
    for n, x in zip(names, np.clip(u, 0.0, 1.0)):
        lo, hi = box[n]
        v, f = lo + float(x) * (hi - lo), _field(n)
        v = 10.0 ** v if f != n else v
        values[f] = int(round(v)) if isinstance(getattr(base, f), int) else v
    return replace(base, **values)


def unit_from_params(p, names: Sequence[str], bounds) -> np.ndarray:
    """Where p lies in the unit cube of the searched names (clipped; a log field <= 0 maps to 0)."""
    box = {n: (lo, hi) for n, lo, hi in bounds}
    out = []
    for n in names:
        lo, hi = box[n]
        v = float(getattr(p, _field(n)))
        if _field(n) != n:
            v = math.log10(v) if v > 0 else lo
        out.append((v - lo) / (hi - lo))
    return np.clip(np.array(out), 0.0, 1.0)


def identify(train_scenes: Sequence[Scene], simulate: Callable, bounds, start, fit: Sequence[str],
             budget: int = 60, seed: int = 0, initial_points: int | None = None, local_starts: int = 2,
             max_tosses: int | None = None, horizon: int | None = None, identify_gravity: bool = True,
             identify_floor: bool = True, frame_rate: float = FRAME_RATE, rotation_weight: float = ROTATION_WEIGHT,
             log: Callable[[str], None] | None = None) -> dict:
    """Identify an engine's parameters on training tosses; deterministic for a given seed.

    Engine-neutral: `simulate(scene, params, frame_rate)` runs one toss, `start` is a frozen
    dataclass of the engine's parameters (with gravity and floor_z fields), `bounds` its search
    box ((name, low, high); "log10_x" searches field x on a log10 scale; int fields are rounded).

    First the constants with closed-form estimates are measured on all training tosses: gravity
    (fit_gravity) with identify_gravity, the table height (fit_floor) with identify_floor. The
    objective (see `objective`) is evaluated on every training toss, or on a seeded random
    subset of `max_tosses` of them. `budget` evaluations in all: the start point; a coarse
    stage of `initial_points` (default budget // 2) Latin-hypercube points over all searched
    names (seeded by `seed`); then bounded Nelder-Mead over the continuous names from each of
    the `local_starts` best coarse points in turn (int names such as substeps stay at that
    point's value), each with an equal share of what is left. Several local starts because the
    objective is rough: a bounce on a corner is chaotic, so one descent often stalls in a dent.
    The best point seen is returned, so the objective never ends above the start's.
    Returns {"params", "objective", "start_objective", "evaluations", "seconds", "fitted",
    "fit_tosses", "history": [(objective, params dict), ...], ...}.
    """
    names = _searched(train_scenes, bounds, fit, budget)
    t0 = time.perf_counter()
    measured = {"gravity": fit_gravity(train_scenes, frame_rate) if identify_gravity else None,
                "floor_z": fit_floor(train_scenes, frame_rate) if identify_floor else None}
    start = replace(start, **{k: v for k, v in measured.items() if v is not None})
    scenes = _fit_tosses(train_scenes, max_tosses, seed)
    evaluate = _Evaluations(lambda p: objective(p, scenes, frame_rate, rotation_weight, simulate, horizon),
                            budget, start, log)
    start_value = evaluate(start)
    coarse = _coarse_stage(evaluate, names, start, bounds, seed, budget // 2 if initial_points is None else initial_points)
    _local_stage(evaluate, coarse, names, start, bounds, local_starts, budget)
    return {"params": evaluate.best, "objective": evaluate.best_value, "start_objective": start_value,
            "evaluations": len(evaluate.cache), "seconds": time.perf_counter() - t0, "fitted": names,
            "fit_tosses": len(scenes), "horizon": horizon, "rotation_weight": rotation_weight,
            "history": evaluate.history}


def _searched(train_scenes: Sequence[Scene], bounds, fit: Sequence[str], budget: int) -> list[str]:
    """The names to search, in the order of `bounds`; ValueError for a search that cannot run."""
    if not train_scenes:
        raise ValueError("no training tosses to fit the baseline on")
    known = [n for n, _, _ in bounds]
    names = [n for n in known if n in fit]
    unknown = set(fit) - set(names)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; fittable: {', '.join(known)}")
    if budget < 1:
        raise ValueError("budget must be >= 1")
    return names


def _fit_tosses(train_scenes: Sequence[Scene], max_tosses: int | None, seed: int) -> list[Scene]:
    """The tosses the objective runs on: all, or a seeded random max_tosses of them."""
    scenes = list(train_scenes)
    if max_tosses is not None and len(scenes) > max_tosses:
        pick = np.random.default_rng([seed, 1]).choice(len(scenes), max_tosses, replace=False)
        scenes = [scenes[i] for i in sorted(pick)]
    return scenes


class _BudgetSpent(Exception):
    pass


class _Evaluations:
    """The objective at parameter sets, each computed once and at most `cap` in all (then
    _BudgetSpent); remembers every value in order and the best set seen."""

    def __init__(self, objective_of: Callable, budget: int, start, log: Callable[[str], None] | None):
        self.objective_of, self.budget, self.cap, self.log = objective_of, budget, budget, log
        self.cache: dict[tuple, float] = {}
        self.history: list[tuple[float, dict]] = []
        self.best_value, self.best = math.inf, start

    def __call__(self, p) -> float:
        key = tuple(round(v, 12) if isinstance(v, float) else v for v in p.to_dict().values())
        if key not in self.cache:
            if len(self.cache) >= self.cap:
                raise _BudgetSpent
            value = self.cache[key] = self.objective_of(p)
            self.history.append((value, p.to_dict()))
            if value < self.best_value:
                self.best_value, self.best = value, p
            if self.log:
                self.log(f"baseline fit {len(self.cache)}/{self.budget}: {value:.3f} at {_short(p)}")
        return self.cache[key]


def _coarse_stage(evaluate: _Evaluations, names: list[str], start, bounds, seed: int,
                  points: int) -> list[tuple[float, np.ndarray]]:
    """The objective at `points` Latin-hypercube points of the unit cube of `names` (seeded by
    seed), until the budget is spent: [(value, point)]."""
    coarse: list[tuple[float, np.ndarray]] = []
    try:
        if points > 0 and names:
            for u in qmc.LatinHypercube(len(names), seed=seed).random(points):
                coarse.append((evaluate(params_from_unit(u, names, start, bounds)), u))
    except _BudgetSpent:
        pass
    return coarse


def _local_stage(evaluate: _Evaluations, coarse: list[tuple[float, np.ndarray]], names: list[str], start, bounds,
                 local_starts: int, budget: int) -> None:
    """Bounded Nelder-Mead over the continuous names from each of the best `local_starts`
    coarse points in turn (from the start if there were none), each with an equal share of the
    evaluations left."""
    ints = [isinstance(getattr(start, _field(n)), int) for n in names]
    free = [i for i, is_int in enumerate(ints) if not is_int]
    seeds = [u for _, u in sorted(coarse, key=lambda c: c[0])[:max(local_starts, 0)]]
    if not seeds and names:  # no coarse stage: descend from the start
        seeds = [unit_from_params(start, names, bounds)]
    for k, u0 in enumerate(seeds if free else []):
        evaluate.cap = len(evaluate.cache) + (budget - len(evaluate.cache)) // (len(seeds) - k)
        x0 = u0[free]

        def f(x, u0=u0):
            u = u0.copy()
            u[free] = x
            return evaluate(params_from_unit(u, names, start, bounds))

        simplex = np.vstack([x0] + [np.clip(x0 + 0.15 * np.eye(len(free))[i] * (1 if x0[i] < 0.85 else -1), 0, 1)
                                    for i in range(len(free))])
        try:
            minimize(f, x0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * len(free),
                     options={"initial_simplex": simplex, "maxfev": 10 * budget, "xatol": 1e-3, "fatol": 1e-3})
        except _BudgetSpent:
            pass


def _short(p) -> str:
    """The searched-for values of a parameter set, for the log."""
    skip = {"gravity", "floor_z"}
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in p.to_dict().items() if k not in skip)
