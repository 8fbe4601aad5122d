"""Speed against accuracy, fairly: PyBullet's own front beside the learned one, on the same scenes.

For each `datagen toss` dataset given (e.g. single-object and 3-10-object MOVi-A test scenes),
PyBullet simulates the scenes again from the dataset's config and seed at every physics rate and
solver-iteration count asked, once with a fresh client per scene (what `datagen toss` does) and
once with one client reused (emptied with resetSimulation: a program simulating many scenes can
do that); every zoo model asked rolls the same scenes out from their first 3 frames, with its
card's rollout options at each precision and with and without compiled code. Everything is
scored against the dataset (the learned models' reference: PyBullet at the data's own settings)
with the MOVi-A metrics, and timed in rounds that alternate PyBullet and the learned rollouts, so
that a change of the machine's load hits both; the best round counts. One thread throughout.

Prints the CPU's features, the machine's load, which precision `--autocast auto` takes here, one
table per dataset (and, for each learned row, the cheapest PyBullet setting at least as accurate
in position, with the ratio of costs: above 1 the learned model is cheaper), and draws one
Pareto figure (cost against error, both fronts).

    python benchmarks/speed_front.py --data data/single_test0 --data data/multi_test \\
        --json docs/figures/speed_front.json --plot docs/figures/speed_front.png
    python benchmarks/speed_front.py --data DIR --rates 60,240 --iterations 10,50 --run movi_a_fast --limit 20
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import pybullet as pb
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent.parent), str(Path(__file__).resolve().parent)]

from bench_learned_vs_physics import pareto_front, pybullet_specs  # noqa: E402
from datagen.toss import simulate  # noqa: E402
from gns.checkpoint import default_options, load_simulator  # noqa: E402
from gns.evaluate import load_split, rollout_scenes  # noqa: E402
from gns.speedups import MARGIN, bf16_speedup, cpu_line, resolve_autocast  # noqa: E402
from gns.metrics import evaluate_scenes  # noqa: E402

RATES = (24, 36, 60, 120, 240, 480, 960)      # physics steps per second; multiples of MOVi-A's 12 fps
ITERATIONS = (5, 10, 20, 50)
PRECISIONS = {"f32": "none", "bf16": "bf16"}
SINGLE_RUNS = ("movi_a", "movi_a_fast", "movi_a_multi")
MULTI_RUNS = ("movi_a_multi", "movi_a_fast")   # the single-object model beside the one made for crowds


def load_line() -> str:
    try:
        return "load average " + " / ".join(f"{v:.2f}" for v in os.getloadavg()) + " (1 / 5 / 15 min)"
    except OSError:
        return "load average unknown"


class Physics:
    """PyBullet at one rate and iteration count, fresh client per scene or one reused."""

    def __init__(self, cfg: dict, specs: list, rate: int, iterations: int, reuse: bool):
        frame_rate = int(cfg["scene"]["frame_rate"])
        if rate % frame_rate:
            raise SystemExit(f"error: --rates {rate}: a physics rate must be a multiple of the data's {frame_rate} fps")
        self.cfg = {**cfg, "physics": {**cfg["physics"], "rate": rate, "solver_iterations": iterations}}
        self.specs, self.reuse = specs, reuse
        self.label = f"PyBullet {rate} Hz, {iterations} it, {'one client' if reuse else 'fresh client'}"
        self.row = {"family": "pybullet", "rate": rate, "iterations": iterations, "client": "reused" if reuse else "fresh"}

    def __call__(self) -> list:
        if not self.reuse:
            return [simulate(s, self.cfg) for s in self.specs]
        c = pb.connect(pb.DIRECT)
        try:
            return [simulate(s, self.cfg, client=c) for s in self.specs]
        finally:
            pb.disconnect(c)


class Learned:
    """A zoo model rolled out with its card's options, at one precision, compiled or not."""

    def __init__(self, run: str, precision: str, compiled: bool, scenes, ds):
        options = default_options(run).replace(autocast=PRECISIONS[precision], compile=compiled)
        self.sim, _ = load_simulator(run, "cpu", options)
        self.scenes, self.ds = scenes, ds
        # what --autocast auto takes for this network's width on this CPU: the precision a user gets
        auto = resolve_autocast("auto", self.sim.network.decoder[0].in_features)
        described = options.replace(autocast="none", compile=False).describe() or "no options"
        self.label = f"{run} {precision}{', compiled' if compiled else ''}"
        self.row = {"family": "learned", "run": run, "precision": precision, "compiled": compiled,
                    "options": described, "auto_takes": "bf16" if auto == "bf16" else "f32"}

    def __call__(self) -> list:
        return rollout_scenes(self.sim, self.scenes, self.ds.meshes, self.ds.frame_rate, progress=False)


def measure(jobs: list, repeats: int) -> tuple[list[float], list[list]]:
    """Warm each job up once (compiling, filling caches), then `repeats` rounds over all jobs in
    turn; returns the best seconds of each and its last output."""
    for job in jobs:
        job()
    best, out = [float("inf")] * len(jobs), [None] * len(jobs)
    for _ in range(repeats):
        for k, job in enumerate(jobs):
            t0 = time.perf_counter()
            out[k] = job()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best, out


def dataset_rows(data: str, a) -> dict:
    ds, scenes = load_split(data, a.split, a.limit, None)
    cfg, specs = pybullet_specs(ds, scenes, a.split)
    crowded = max(sc.positions.shape[1] for sc in scenes) > 1
    runs = a.run or (MULTI_RUNS if crowded else SINGLE_RUNS)
    jobs = [Physics(cfg, specs, r, it, reuse) for reuse in (False, True) for r in a.rates for it in a.iterations]
    jobs += [Learned(run, p, c, scenes, ds) for run in runs for p in a.precisions for c in a.compiled]
    print(f"{data}: {len(scenes)} {a.split} scenes, {len(jobs)} settings, best of {a.repeats} rounds", flush=True)
    seconds, outputs = measure(jobs, a.repeats)
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    rows = []
    for job, s, pred in zip(jobs, seconds, outputs):
        # PyBullet simulates every frame after the first; the learned model those after the 3 given
        frames = sum(sc.num_frames - (1 if job.row["family"] == "pybullet" else 3) for sc in scenes)
        r = evaluate_scenes(pred, scenes, ds.meshes, floor_z=floor_z)
        rows.append({**job.row, "label": job.label, "ms_per_simulated_second": 1e3 * s * ds.frame_rate / frames,
                     "position_error_pct": r["position_error_pct"], "rotation_error_deg": r["rotation_error_deg"],
                     "penetration_pct": r["penetration_pct"]})
    objects = [sc.positions.shape[1] for sc in scenes]
    return {"data": data, "scenes": len(scenes), "objects": [min(objects), max(objects)],
            "frame_rate": ds.frame_rate, "truth": f"PyBullet {cfg['physics']['rate']} Hz, "
            f"{cfg['physics']['solver_iterations']} it", "rows": rows}


def cheapest_as_good(row: dict, rows: list[dict]) -> dict | None:
    """The cheapest PyBullet row whose position error is at most this row's."""
    ok = [r for r in rows if r["family"] == "pybullet" and r["position_error_pct"] <= row["position_error_pct"]]
    return min(ok, key=lambda r: r["ms_per_simulated_second"]) if ok else None


def print_table(result: dict) -> None:
    lo, hi = result["objects"]
    print(f"\n{result['data']}: {result['scenes']} scenes of {lo}-{hi} objects, against {result['truth']} (the data)")
    print("| simulator | ms per simulated s | position % | rotation deg | penetration % | "
          "cheapest PyBullet as accurate (position) | its cost / this cost |")
    print("|---|---|---|---|---|---|---|")
    for r in sorted(result["rows"], key=lambda r: (r["family"] == "learned", r["ms_per_simulated_second"])):
        match = cheapest_as_good(r, result["rows"]) if r["family"] == "learned" else None
        versus = (f"{match['label'][len('PyBullet '):]} | {match['ms_per_simulated_second'] / r['ms_per_simulated_second']:.2f}"
                  if match else ("none reaches it | -" if r["family"] == "learned" else "| "))
        mark = " (auto)" if r["family"] == "learned" and r["precision"] == r["auto_takes"] else ""
        print(f"| {r['label']}{mark} | {r['ms_per_simulated_second']:.2f} | {r['position_error_pct']:.2f} | "
              f"{r['rotation_error_deg']:.2f} | {r['penetration_pct']:.3f} | {versus} |")


def plot(results: list[dict], path: str) -> Path:
    """One row a dataset, position and rotation error against cost (log), PyBullet's fresh and
    reused client as two fronts, the learned points labelled and their front drawn."""
    from gns.charts import label_points, log_x_axis
    from gns.plots import new_figure, save_figure
    fig = new_figure((11, 4.6 * len(results) + 0.4))
    axes = np.atleast_2d(fig.subplots(len(results), 2, squeeze=False))
    styles = {("pybullet", "fresh"): ("C0", "o", "PyBullet, fresh client"),
              ("pybullet", "reused"): ("C2", "s", "PyBullet, one client"), ("learned", None): ("C3", "D", "learned")}
    fronts = []
    for res, row_axes in zip(results, axes):
        lo, hi = res["objects"]
        for ax, key, what in zip(row_axes, ("position_error_pct", "rotation_error_deg"),
                                 ("position error [% of size]", "rotation error [deg]")):
            for (family, client), (colour, marker, name) in styles.items():
                pts = [r for r in res["rows"] if r["family"] == family and r.get("client") == client]
                # the data's own setting scores 0 and has no place on a log-free error axis: kept, at 0
                xs, ys = [r["ms_per_simulated_second"] for r in pts], [r[key] for r in pts]
                ax.scatter(xs, ys, color=colour, marker=marker, s=22 if family == "pybullet" else 40, zorder=3,
                           label=name, alpha=0.75 if family == "pybullet" else 1.0)
                front = pareto_front([-x for x in xs], ys)
                fx, fy = [xs[i] for i in front], [ys[i] for i in front]
                ax.step(fx, fy, where="post", color=colour, lw=0.9, zorder=2)
                # only each front's points are named: the rest are the table's
                if family == "learned":
                    names = [f"{pts[i]['run']} {pts[i]['precision']}{' compiled' if pts[i]['compiled'] else ''}"
                             for i in front]
                elif client == "reused":   # the stronger PyBullet: one label a rate, at its cheapest point
                    seen = set()
                    keep = [k for k, i in enumerate(front) if not (pts[i]["rate"] in seen or seen.add(pts[i]["rate"]))]
                    fx, fy = [fx[k] for k in keep], [fy[k] for k in keep]
                    names = [f"{pts[front[k]]['rate']} Hz/{pts[front[k]]['iterations']}" for k in keep]
                else:
                    continue
                fronts.append((ax, fx, fy, names, 6 if family == "learned" else 5.5))
            log_x_axis(ax)
            ax.set_xlabel("ms per simulated second per scene (one thread; left is cheaper)")
            ax.set_ylabel(what)
            ax.set_title(f"{res['scenes']} scenes of {lo}-{hi} objects" if lo != hi else
                         f"{res['scenes']} scenes of {lo} object{'s' if lo > 1 else ''}", fontsize=9)
            ax.grid(alpha=0.3, which="both")
    for ax, fx, fy, names, size in fronts:   # once the axes' scales are final
        label_points(ax, fx, fy, names, fontsize=size)
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, fontsize=7, loc="lower center", ncol=3, frameon=False)
    fig.suptitle("speed against accuracy on the same scenes, against PyBullet at the data's settings "
                 "(lower left is better; lines: each family's front;\nPyBullet's named by physics rate/solver iterations)", fontsize=9)
    fig.tight_layout(rect=(0, 0.05 / len(results), 1, 1))
    return save_figure(fig, path, dpi=130)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", help="a datagen toss dataset (repeat: one table each)")
    p.add_argument("--run", action="append",
                   help=f"zoo model or run folder (repeat; default: {', '.join(SINGLE_RUNS)} on single-object "
                        f"scenes, {', '.join(MULTI_RUNS)} where scenes hold several)")
    p.add_argument("--split", default="test")
    p.add_argument("--limit", type=int, help="first N scenes of each dataset only")
    p.add_argument("--rates", default=",".join(map(str, RATES)), help="PyBullet physics rates, Hz")
    p.add_argument("--iterations", default=",".join(map(str, ITERATIONS)), help="PyBullet solver iterations")
    p.add_argument("--precisions", default="f32,bf16", help="learned: f32 and/or bf16")
    p.add_argument("--compile", choices=("both", "no", "yes"), default="both",
                   help="learned: plain network, compiled code (torch.compile with freezing, gns eval --compile), or both")
    p.add_argument("--repeats", type=int, default=2, help="timed rounds, best taken (default 2)")
    p.add_argument("--json", help="also write the rows here")
    p.add_argument("--plot", help="also draw the Pareto figure here (PNG)")
    p.add_argument("--replot", metavar="JSON", help="only draw --plot from an earlier --json (no timing)")
    a = p.parse_args(argv)
    if a.replot:
        if not a.plot:
            p.error("--replot needs --plot")
        print(f"plot: {plot(json.loads(Path(a.replot).read_text())['results'], a.plot)}")
        return 0
    if not a.data:
        p.error("--data is required (or --replot JSON --plot PNG)")
    try:
        a.rates = [int(v) for v in a.rates.split(",")]
        a.iterations = [int(v) for v in a.iterations.split(",")]
    except ValueError:
        p.error("--rates and --iterations are comma lists of whole numbers")
    a.precisions = a.precisions.split(",")
    a.compiled = {"both": (False, True), "no": (False,), "yes": (True,)}[a.compile]
    if set(a.precisions) - set(PRECISIONS):
        p.error(f"--precisions: one or both of {', '.join(PRECISIONS)}")
    torch.set_num_threads(1)
    header = {"cpu": cpu_line(), "load_before": load_line(), "threads": 1,
              "bf16_matmul_speedup": bf16_speedup(128)}
    print(f"{header['cpu']}\n{header['load_before']}; one thread\n"
          f"bf16 matrix product of a width-128 network layer: {header['bf16_matmul_speedup']:.2f}x float32's speed "
          f"(--autocast auto takes bf16 at >= {MARGIN}x; each model's choice in its rows)")
    results = [dataset_rows(d, a) for d in a.data]
    header["load_after"] = load_line()
    print(header["load_after"])
    for res in results:
        print_table(res)
    if a.json:
        Path(a.json).write_text(json.dumps({**header, "results": results, "repeats": a.repeats}, indent=1) + "\n")
    if a.plot:
        print(f"plot: {plot(results, a.plot)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
