"""Two rollout settings on the same scenes, scene by scene: the paired difference of their errors with
a bootstrap 95% interval, per set of scenes and over all of them.

A model's mean on 400 MOVi-A scenes moves with the sample of scenes (one model on four sets of 400
from the same generator: 9.9 to 10.8 points), more than many differences worth knowing; each scene's
error, though, is largely the scene's (small, fast or spinning objects are hard for any model), so
the per-scene difference A - B is far less noisy than either mean.
An interval that excludes 0 says which is better on scenes like these (experiments/log.md).

    python benchmarks/compare_rollouts.py --a movi_a:d1 --b movi_a \\
        --data data/movi_a_32000 --data data/movi_a_seed1:test --data data/movi_a_seed1:valid \\
        --data data/movi_a_seed1:train --free-flight --free-clearance 0.5 --compile --json out.json

A and B: RUN[+MEMBER...][:GROUP], a run folder, checkpoint or shipped model; "+" joins an ensemble
(`gns eval --ensemble`), ":GROUP" a `--symmetrize` group. --data DIR[:SPLIT], repeatable (default
split test). Both roll out with `gns eval`'s code (gns.evaluate.evaluate_run), bf16 where it measures
faster (--autocast auto), one thread.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gns.checkpoint import CheckpointError  # noqa: E402
from gns.config import ConfigError  # noqa: E402
from gns.evaluate import evaluate_run, write_json  # noqa: E402
from gns.symmetry import SYMMETRY_GROUPS  # noqa: E402
from plumbing import DataError  # noqa: E402

METRICS = {"position_error_pct": "position %", "rotation_error_deg": "rotation deg"}
GROUPS = tuple(SYMMETRY_GROUPS)


def parse_setting(text: str) -> tuple[str, list[str], str | bool]:
    """RUN[+MEMBER...][:GROUP] -> (run, ensemble members, symmetrize group or False)."""
    runs, _, group = text.partition(":")
    first, *members = runs.split("+")
    if not first or not all(members):
        raise SystemExit(f"error: {text!r}: an empty run name; expected RUN[+MEMBER...][:GROUP]")
    if group and group not in GROUPS:
        raise SystemExit(f"error: {text!r}: unknown symmetry group {group!r}; known: {', '.join(GROUPS)}")
    return first, members, group or False


def parse_data(text: str) -> tuple[str, str]:
    """DIR[:SPLIT] -> (dir, split)."""
    folder, _, split = text.partition(":")
    return folder, split or "test"


def paired(a: list[dict], b: list[dict], metric: str) -> np.ndarray:
    """Per-scene differences A - B of `metric`, the scenes matched by scene_id."""
    theirs = {row["scene_id"]: row[metric] for row in b}
    if set(theirs) != {row["scene_id"] for row in a}:
        raise SystemExit("error: A and B scored different scenes (a diverged rollout is left out of one); "
                         "compare on scenes both finish")
    return np.array([row[metric] - theirs[row["scene_id"]] for row in a])


def interval(diff: np.ndarray, rng: np.random.Generator, resamples: int) -> tuple[float, float, float]:
    """Mean of the differences and its bootstrap 95% interval (scenes resampled with replacement)."""
    means = diff[rng.integers(0, len(diff), (resamples, len(diff)))].mean(axis=1)
    return float(diff.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--a", required=True, metavar="RUN[+M][:GROUP]", help="the first setting")
    p.add_argument("--b", required=True, metavar="RUN[+M][:GROUP]", help="the second setting")
    p.add_argument("--data", action="append", required=True, metavar="DIR[:SPLIT]",
                   help="a dataset and split to roll out (default split test); repeat for several sets")
    p.add_argument("--limit", type=int, metavar="N", help="first N scenes of each set only")
    p.add_argument("--free-flight", action="store_true", help="as gns eval --free-flight")
    p.add_argument("--free-clearance", type=float, metavar="D", help="as gns eval --free-clearance")
    p.add_argument("--compile", action="store_true", help="as gns eval --compile (frozen, compiled rollouts)")
    p.add_argument("--resamples", type=int, default=4000, help="bootstrap resamples (default 4000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--json", help="also write the per-set rows and every scene's errors here")
    a = p.parse_args(argv)
    if a.free_clearance is not None and not a.free_flight:
        p.error("--free-clearance sets free flight's height: it needs --free-flight")
    if a.resamples < 100:
        p.error(f"--resamples must be >= 100, got {a.resamples}")
    settings = {"A": parse_setting(a.a), "B": parse_setting(a.b)}
    sets = [parse_data(d) for d in a.data]
    torch.set_num_threads(1)
    rng = np.random.default_rng(a.seed)
    scenes, rows = {}, []
    for folder, split in sets:
        for name, (run, members, group) in settings.items():
            try:
                results, *_ = evaluate_run(run, folder, split, a.limit, progress=False, symmetrize=group,
                                           free_flight=a.free_flight, autocast="auto", compile=a.compile,
                                           ensemble=members, free_clearance=a.free_clearance)
            except (DataError, CheckpointError, ConfigError, ValueError) as e:
                raise SystemExit(f"error: {name} on {folder}:{split}: {e}") from None
            scenes[(folder, split, name)] = results["per_scene"]
    diffs = {m: [] for m in METRICS}
    for folder, split in sets + [("all", "")]:
        row = {"data": folder, "split": split}
        for m in METRICS:
            if folder == "all":
                d = np.concatenate(diffs[m])
                means = {n: float(np.mean([r[m] for (_, _, k), per in scenes.items() if k == n for r in per]))
                         for n in settings}
            else:
                d = paired(scenes[(folder, split, "A")], scenes[(folder, split, "B")], m)
                diffs[m].append(d)
                means = {n: float(np.mean([r[m] for r in scenes[(folder, split, n)]])) for n in settings}
            mean, low, high = interval(d, rng, a.resamples)
            row[m] = {"A": means["A"], "B": means["B"], "A_minus_B": mean, "low": low, "high": high}
        row["scenes"] = len(d)
        rows.append(row)
    print(f"A = {a.a}, B = {a.b}; free flight {a.free_flight}, clearance {a.free_clearance}; per-scene means, "
          f"A - B with its bootstrap 95% interval ({a.resamples} resamples)")
    print("| scenes | " + " | ".join(f"{t} A / B | A - B [95%]" for t in METRICS.values()) + " |")
    print("|---|" + "---|---|" * len(METRICS))
    for row in rows:
        cells = [f"{row[m]['A']:.2f} / {row[m]['B']:.2f} | {row[m]['A_minus_B']:+.2f} "
                 f"[{row[m]['low']:+.2f}, {row[m]['high']:+.2f}]" for m in METRICS]
        label = f"{row['data']}:{row['split']}" if row["split"] else "all"
        print(f"| {label} ({row['scenes']}) | " + " | ".join(cells) + " |")
    if a.json:
        per_scene = {f"{f}:{s}:{n}": per for (f, s, n), per in scenes.items()}
        write_json(a.json, {"a": a.a, "b": a.b, "free_flight": a.free_flight, "free_clearance": a.free_clearance,
                            "compile": a.compile, "seed": a.seed, "resamples": a.resamples, "rows": rows,
                            "per_scene": per_scene})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
