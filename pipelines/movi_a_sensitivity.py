"""How predictable a PyBullet toss is: the error of exact physics started from a slightly wrong state.

A learned simulator is scored against one sample of a chaotic system: a beveled cube that lands
on an edge goes one way or the other on a hair's difference. This re-simulates every scene of a
datagen split with the generator's own engine, world and parameters (datagen.toss, the
recorded config), changes one thing by a small amount right after the last frame a GNS is given
(frame HISTORY - 1 = 2), and scores the result with `gns eval`'s metrics. The unperturbed row
reproduces the data and must score 0 (a check that the study runs the data's physics). What the
other rows score is the error a simulator with perfect physics makes when its state or its
material is off by that much: the floor a learned model's error is to be read against
(experiments/log.md).

    python -m pipelines.movi_a_sensitivity --data data/movi_a_4000 [--split test] [--limit N] [--out DIR]
        [--run movi_a ...]   # also the learned models' rollouts, in the same table

Perturbations (each scene draws its own random directions and signs from --seed and its index):
  turn E deg       the pose turned by E degrees about a random axis through the centre of mass
  shift E %        the centre moved by E% of the object's size in a random direction
  velocity E %     the linear velocity changed by E% of its magnitude in a random direction
  spin E deg/frame an angular velocity of E degrees per frame about a random axis added
  friction E %     the object's friction scaled by 1 +- E/100 (random sign)
  restitution E %  the object's restitution scaled by 1 +- E/100 (random sign)
The contact kinds stand in for a learned simulator's own errors, which it makes at every step
in contact (pipelines/one_step.py: 86% of its one-step rotation error), not once; its next step
reads its velocity off its own last two frames, so a wrong frame is a wrong velocity too:
  contact_turn E   after every step in contact (from the first predicted frame on; the step's
                   centre acceleration off gravity by more than train.contact_threshold x g, as
                   gns.data.in_contact), the pose turned by E degrees about a random axis and
                   E degrees per frame of spin added about the same axis
  contact_shift E  the same with the centre moved by E% of the size and the velocity changed by
                   E% of the size per frame in the same direction
Parts joined by '+' are applied together: contact_turn:2+contact_shift:1.5 is one row.
A size written MEAN~SIGMA is drawn anew at each application from a log-normal law of that mean
and log-standard deviation: a learned model's contact-step errors are heavy-tailed (median about
half the mean, the 99th percentile 7x it), which a fixed size does not mimic.
Writes results.json (every row's metrics, the data's fingerprint, the seed) and report.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plumbing import atomic_file, DataError
from datagen.shards import Dataset
from gns.evaluate import evaluate_run, score_predictions
from gns.network import HISTORY
from pipelines.common import guarded, say

KINDS = ("exact", "turn", "shift", "velocity", "spin", "friction", "restitution", "contact_turn", "contact_shift")
UNITS = {"exact": "", "turn": "deg", "shift": "% of size", "velocity": "%", "spin": "deg/frame",
         "friction": "%", "restitution": "%", "contact_turn": "deg a contact step",
         "contact_shift": "% of size a contact step"}
DEFAULT = ("exact:0", "turn:0.1", "turn:1", "turn:3", "shift:1", "velocity:1", "spin:1", "friction:10",
           "restitution:10")


@dataclass(frozen=True)
class Perturbation:
    """One row of the study: KIND:SIZE[~SIGMA], or several joined by '+' and applied together.
    parts: (kind, mean size, log-normal sigma; 0 = a fixed size)."""
    parts: tuple[tuple[str, float, float], ...]

    @classmethod
    def parse(cls, text: str) -> "Perturbation":
        parts = []
        for piece in text.split("+"):
            kind, _, size = piece.partition(":")
            size, _, sigma = size.partition("~")
            if kind not in KINDS:
                raise DataError(f"unknown perturbation {kind!r} in {text!r}; known: {', '.join(KINDS)}")
            try:
                value, spread = float(size or 0), float(sigma or 0)
            except ValueError:
                raise DataError(f"perturbation {text!r}: size {piece.partition(':')[2]!r} is not a number") from None
            if not (np.isfinite(value) and np.isfinite(spread)) or value < 0 or spread < 0:
                raise DataError(f"perturbation {text!r}: size must be a finite number >= 0")
            parts.append((kind, value, spread))
        return cls(tuple(parts))

    @property
    def kind(self) -> str:
        return "+".join(k for k, _, _ in self.parts)

    @property
    def size(self) -> float | None:
        return self.parts[0][1] if len(self.parts) == 1 else None

    @property
    def label(self) -> str:
        return " + ".join("exact (none)" if k == "exact" else f"{k} {v:g}{f'~{s:g}' if s else ''} {UNITS[k]}"
                          for k, v, s in self.parts)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _turn(quat_xyzw, axis: np.ndarray, degrees: float):
    from scipy.spatial.transform import Rotation
    return (Rotation.from_rotvec(np.radians(degrees) * axis) * Rotation.from_quat(quat_xyzw)).as_quat()


def perturber(p: Perturbation, rng: np.random.Generator, frame: int, frame_rate: float, objects: list,
              gravity: np.ndarray):
    """A datagen.toss `after_frame` hook applying p to every object (datagen.scenes.ObjectSpec)
    once frame `frame` is recorded (the contact kinds: after every later frame a step in contact made)."""
    import torch

    from datagen.toss import pb
    from gns.config import TrainConfig
    from gns.data import in_contact
    g_step = torch.as_tensor(np.asarray(gravity, float) / frame_rate ** 2)
    centres: list[list[np.ndarray]] = [[] for _ in objects]

    def contact_step(j: int, t: int) -> bool:
        """Did the step to frame t (> frame) touch something: the training's test
        (gns.data.in_contact) of the centre's second difference over frames t-2..t."""
        if t <= frame or len(centres[j]) < 3:
            return False
        return bool(in_contact(torch.as_tensor(np.stack(centres[j][-3:])), g_step, TrainConfig.contact_threshold)[1])

    def hook(t, c, bodies):
        for j, (b, o) in enumerate(zip(bodies, objects)):
            pos, quat = pb.getBasePositionAndOrientation(b, physicsClientId=c)
            pos = np.array(pos)
            centres[j].append(pos)
            touched = contact_step(j, t)
            vel, ang = (np.array(v) for v in pb.getBaseVelocity(b, physicsClientId=c))
            moved = False
            for kind, mean, sigma in p.parts:
                applies = touched if kind.startswith("contact") else (t == frame and kind != "exact")
                if not applies:
                    continue
                # log-normal of this mean: mu = ln(mean) - sigma^2 / 2
                size = mean * float(np.exp(sigma * rng.normal() - sigma ** 2 / 2)) if sigma else mean
                if kind == "friction":
                    pb.changeDynamics(b, -1, lateralFriction=o.friction * (1 + rng.choice((-1, 1)) * size / 100),
                                      physicsClientId=c)
                    continue
                if kind == "restitution":
                    # from the spec: getDynamicsInfo reports 0 restitution for maximal-coordinate bodies
                    pb.changeDynamics(b, -1, restitution=o.restitution * (1 + rng.choice((-1, 1)) * size / 100),
                                      physicsClientId=c)
                    continue
                if size == 0:   # a reset to the same state is not quite a no-op in Bullet
                    continue
                moved = True
                axis = _unit(rng)
                if kind in ("turn", "contact_turn"):
                    quat = _turn(quat, axis, size)
                if kind == "contact_turn" or kind == "spin":
                    ang = ang + axis * np.radians(size) * frame_rate
                if kind in ("shift", "contact_shift"):
                    pos = pos + axis * size / 100 * o.scale
                if kind == "contact_shift":
                    vel = vel + axis * size / 100 * o.scale * frame_rate
                if kind == "velocity":
                    vel = vel + axis * size / 100 * np.linalg.norm(vel)
            if moved:
                pb.resetBasePositionAndOrientation(b, pos.tolist(), list(quat), physicsClientId=c)
                pb.resetBaseVelocity(b, vel.tolist(), ang.tolist(), physicsClientId=c)
    return hook


def resimulate(ds: Dataset, scenes: list, p: Perturbation, seed: int, frame: int = HISTORY - 1) -> list:
    """Every scene simulated again from its recorded spec (datagen.scenes.sample_scene with the
    dataset's config and seed), perturbed by p after `frame`."""
    from datagen.scenes import sample_scene
    from datagen.toss import simulate
    cfg, data_seed = ds.meta["config"], int(ds.meta["seed"])
    out = []
    for sc in scenes:
        split, _, index = str(sc.attrs["scene_id"]).partition("-")
        spec = sample_scene(cfg, data_seed, split, int(index))
        rng = np.random.default_rng([seed, int(index), *(KINDS.index(k) for k, _, _ in p.parts)])
        hook = perturber(p, rng, frame, ds.frame_rate, spec.objects, np.asarray(ds.meta["gravity"], float))
        out.append(simulate(spec, cfg, after_frame=hook))
    return out


METRICS = ("position_error_pct", "rotation_error_deg", "penetration_pct")


def _row(label: str, kind: str, size, res: dict) -> dict:
    return {"perturbation": kind, "size": size, "label": label, **{k: res[k] for k in METRICS},
            "horizons": {h: {k: v[k] for k in METRICS} for h, v in res["horizons"].items()},
            "by_shape": {s: {k: v[k] for k in METRICS} for s, v in res["by_shape"].items()}}


def study(data: str | Path, split: str = "test", limit: int | None = None,
          perturbations: tuple[str, ...] = DEFAULT, seed: int = 0, progress: bool = True,
          runs: tuple[str, ...] = ()) -> dict:
    """Every perturbation's row; with `runs`, also each learned model's rollouts of the same scenes
    (free flight, symmetrized, autocast auto: the options the accuracy tables use)."""
    parsed = [Perturbation.parse(text) for text in perturbations]   # a typo fails before any simulation
    ds = Dataset(data)
    if ds.meta.get("generator") != "datagen toss" or "config" not in ds.meta:
        raise DataError(f"{data}: not made by `datagen toss` (no generator config to re-simulate with)")
    if split not in ds.splits:
        raise DataError(f"{data}: no scenes in split {split!r}; it has {', '.join(ds.splits) or 'none'}")
    scenes = ds.load(split, limit)
    rows = []
    for p in parsed:
        t0 = time.perf_counter()
        pred = resimulate(ds, scenes, p, seed)
        res = score_predictions(pred, scenes, ds, time.perf_counter() - t0)
        row = _row(p.label, p.kind, p.size, res)
        rows.append(row)
        if progress:
            say(f"{p.label}: {row['position_error_pct']:.2f}% / {row['rotation_error_deg']:.2f} deg "
                f"({time.perf_counter() - t0:.0f} s, {len(scenes)} scenes)")
    for run in runs:
        res, *_ = evaluate_run(run, data, split, limit, progress=False, free_flight=True, symmetrize=True,
                               autocast="auto")
        rows.append(_row(f"GNS {run} (its own rollout)", "gns", None, res))
        if progress:
            say(f"GNS {run}: {res['position_error_pct']:.2f}% / {res['rotation_error_deg']:.2f} deg")
    return {"data": str(data), "data_fingerprint": ds.meta.get("fingerprint"), "split": split,
            "num_scenes": len(scenes), "seed": seed, "perturbed_after_frame": HISTORY - 1, "rows": rows}


def report(results: dict) -> str:
    shapes = sorted(results["rows"][0]["by_shape"])
    horizons = sorted(results["rows"][0]["horizons"], key=int)
    head = ["perturbation after frame 2", "position %", "rotation deg", "penetration %",
            *(f"rotation deg at {h}" for h in horizons), *(f"{s}: pos % / rot deg" for s in shapes)]
    lines = [f"Exact physics from a perturbed state: {results['num_scenes']} {results['split']} scenes of "
             f"`{results['data']}` (fingerprint {str(results['data_fingerprint'])[:16]}), seed {results['seed']}.",
             "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results["rows"]:
        cells = [r["label"], f"{r['position_error_pct']:.2f}", f"{r['rotation_error_deg']:.2f}",
                 f"{r['penetration_pct']:.3f}", *(f"{r['horizons'][h]['rotation_error_deg']:.2f}" for h in horizons),
                 *(f"{r['by_shape'][s]['position_error_pct']:.2f} / {r['by_shape'][s]['rotation_error_deg']:.2f}"
                   for s in shapes)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.movi_a_sensitivity", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="a dataset made by `datagen toss`")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, help="only the first N scenes of the split")
    ap.add_argument("--perturb", nargs="+", default=list(DEFAULT), metavar="KIND:SIZE",
                    help=f"perturbations to run (default: {' '.join(DEFAULT)})")
    ap.add_argument("--seed", type=int, default=0, help="seed of the perturbations' random directions and signs")
    ap.add_argument("--out", type=Path, default=Path("runs/movi_a_sensitivity"), help="folder for results.json and report.md")
    ap.add_argument("--run", action="append", default=[], metavar="RUN",
                    help="also roll out this trained model (run folder or shipped name; repeatable) on the same "
                         "scenes, free flight + symmetrized, as a row of the same table")
    a = ap.parse_args(argv)
    if a.limit is not None and a.limit < 1:
        ap.error("--limit must be >= 1")

    def stages():
        results = study(a.data, a.split, a.limit, tuple(a.perturb), a.seed, runs=tuple(a.run))
        a.out.mkdir(parents=True, exist_ok=True)
        with atomic_file(a.out / "results.json") as tmp:
            tmp.write_text(json.dumps(results, indent=1))
        text = report(results)
        with atomic_file(a.out / "report.md") as tmp:
            tmp.write_text(text)
        print(text)
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
