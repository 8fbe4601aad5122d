"""Stability of a trained GNS at the extremes: a report of gns.stability's checks.

    python -m pipelines.stability --run runs/movi_a_small/run --data runs/movi_a_small/data

- long rollouts: test scenes rolled out 10x their length: finite, rigid, above the floor;
- at rest: every training shape lying still on the floor, 1000 steps: drift below 0.1% of its size;
- extreme inputs (3x speeds, friction and restitution 0 and 1, sizes 0.01x and 100x, 1e4 units
  from the origin, float32 arrays): handled, or named by the range check as outside training.
Writes report.md and results.json (default runs/stability_<run folder name>). Every check
says PASS or FAIL; the exit status is 0 either way, since a failing model is a finding.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from plumbing import check_writable
from gns.stepping import Sleep
from gns.checkpoint import checkpoint_of
from gns.evaluate import load_split, write_json
from gns.stability import REST_DRIFT_PCT, at_rest, extremes, long_rollouts, resting_scene
from gns.spec import ModelSpec
from gns.checkpoint import default_options, load_model, read_checkpoint
from pipelines.common import guarded, say


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def run(run_dir: Path, data: Path, out: Path, limit: int, factor: int, rest_steps: int) -> dict:
    torch.set_num_threads(1)
    check_writable(out)
    ckpt = checkpoint_of(run_dir)
    saved = read_checkpoint(ckpt)
    options = default_options(run_dir)       # a zoo model's scored options, else the defaults
    sim, _ = load_model(saved, options=options)
    spec = ModelSpec.from_dict(saved["spec"])
    ds, scenes = load_split(data, "test", limit, spec.frame_rate)
    floor_z = float(ds.floor["z"]) if ds.floor else None
    say(f"long rollouts: {len(scenes)} scenes, {factor}x their length")
    long = long_rollouts(sim, scenes, ds.meshes, floor_z, factor)
    say("at rest: each shape lying on the floor")
    scale = float(max(spec.ranges["scale"]))
    resting = [resting_scene(shape, scale, ds.meshes, floor_z or 0.0) for shape in spec.shapes]
    rest = at_rest(sim, resting, ds.meshes, rest_steps)
    rest_sleeping = at_rest(sim, resting, ds.meshes, rest_steps, sleep=True)
    say("extreme inputs")
    extreme = extremes(sim, spec, scenes, ds)
    results = {"run": str(run_dir), "checkpoint": str(ckpt), "checkpoint_step": int(saved["step"]),
               "rollout_options": options.to_dict(), "data": str(data), "limit": limit, "factor": factor, "rest_steps": rest_steps, "long_rollouts": long, "at_rest": rest,
               "at_rest_sleeping": {"sleep": dataclasses.asdict(Sleep(sim.options.sleep_fraction)), "rows": rest_sleeping}, "extremes": extreme}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", results)
    (out / "report.md").write_text(report(results, factor) + "\n")
    return results


def report(r: dict, factor: int) -> str:
    long = r["long_rollouts"]
    lines = [f"# Stability at the extremes: `{r['run']}` (step {r['checkpoint_step']})", "",
             f"Made by `python -m pipelines.stability --run {r['run']} --data {r['data']} --limit {r['limit']} "
             f"--factor {r['factor']} --rest-steps {r['rest_steps']}`.", "",
             f"## Long rollouts ({factor}x the test scenes' length, {long['steps']} steps, {long['objects']} objects)", "",
             "| check | measured | verdict |", "|---|---|---|",
             f"| finite | {long['finite']} ({long['finite_scenes_pct']:.0f}% of {long['scenes']} scenes) | "
             f"{_verdict(long['finite'])} |",
             f"| rigid (largest edge-length change, % of size) | {long['distortion_pct']:.2g} | {_verdict(long['rigid'])} |"]
    if "above_floor" in long:
        lines += [f"| centres above the floor (lowest centre height) | {long['min_centre_height']:.3g} | "
                  f"{_verdict(long['above_floor'])} |",
                  f"| deepest floor penetration, % of size (mean) | {long['max_penetration_pct']:.3g} "
                  f"({long['mean_penetration_pct']:.3g}) | reported |"]
    steps = r["at_rest"][0]["steps"]
    lines += ["", f"## At rest ({steps} steps on the floor; criterion: drift below {REST_DRIFT_PCT}% of the size)", "",
              f"| shape | scale | drift after {steps // 10} steps, % of size | drift after {steps} steps | verdict |",
              "|---|---|---|---|---|"]
    sleeping = r["at_rest_sleeping"]
    for x in r["at_rest"]:
        lines.append(f"| {x['shape']} | {x['scale']:g} | {x[f'drift_pct_after_{steps // 10}']:.3g} | "
                     f"{x['drift_pct']:.3g} | {_verdict(x['passed'])} |")
    for x in sleeping["rows"]:
        lines.append(f"| {x['shape']}, rollout with sleeping | {x['scale']:g} | "
                     f"{x[f'drift_pct_after_{steps // 10}']:.3g} | {x['drift_pct']:.3g} | {_verdict(x['passed'])} |")
    lines += ["", f"Sleeping (`gns eval --sleep`, gns.stepping.Sleep): an object sleeps while no vertex moved "
                  f"{sleeping['sleep']['fraction']} x |g| dt^2 in either input step, until an awake object touches it."]
    lines += ["", "## Extreme inputs (handled, or warned as outside training)", "",
              "| input | rollout finite | same as the original, % of size | warnings | verdict |", "|---|---|---|---|---|"]
    for x in r["extremes"]:
        same = f"{x['difference_pct']:.2g}" if "difference_pct" in x else "-"
        warn = "; ".join(x["warnings"]) or "none"
        lines.append(f"| {x['case']} | {x['finite']} | {same} | {warn} | {_verdict(x['passed'])} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.stability", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, type=Path, help="run folder (its latest.pt) or a .pt checkpoint")
    ap.add_argument("--data", required=True, type=Path, help="dataset folder whose test split is used")
    ap.add_argument("--out", type=Path, help="output folder (default runs/stability_<run name>)")
    ap.add_argument("--limit", type=int, default=8, help="test scenes to use (default 8)")
    ap.add_argument("--factor", type=int, default=10, help="long rollouts: times the scene length (default 10)")
    ap.add_argument("--rest-steps", type=int, default=1000, help="steps of the at-rest check (default 1000)")
    a = ap.parse_args(argv)
    name = a.run.name if a.run.name not in ("run", "latest.pt") else a.run.resolve().parent.name
    out = a.out or Path("runs") / f"stability_{name}"

    def stages():
        run(a.run, a.data, out, a.limit, a.factor, a.rest_steps)
        print((out / "report.md").read_text())
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
