"""Learned rollouts against PyBullet on the same test scenes: cost and accuracy, in one run.

PyBullet simulates the test scenes of a `datagen toss` dataset again, from the dataset's own
config and seed (build + step, as `benchmarks/bench_datagen.py` times bare PyBullet, one scene at
a time on one thread); the GNS rolls the same scenes out from their first 3 frames, all scenes
batched, in each variant asked:

  plain     the network on every object, float32
  free      objects out of reach of the floor and of other objects follow the exact inertial
            update, the network runs on the others (`gns eval --free-flight`)
  sleep     resting objects keep their pose and leave the network call (`--sleep`)
  bf16      the network under bfloat16 autocast (`--autocast bf16`)
  compile   the network through torch.compile, its weights read at every call (what training
            compiles; compiled before timing)
  freeze    compile with inductor's freezing, the weights taken as constants at the first call
            (what `gns eval --compile` runs)
  clearD    free flight's clearance D above the floor (`--free-clearance D`; default the floor
            clip): e.g. free+clear0.5
  sym       each step averaged over the floor's 4 mirror symmetries (`--symmetrize`): the most
            accurate rollouts, at 4x the network's work
  d1, c2, c4, d4
            the other averages of `--symmetrize GROUP` (c2: the half turn, 2x the work; experiments/log.md)

joined with "+" (e.g. free+bf16). Several --run give every variant of every model, all in the
same rounds (e.g. a small model against a large one). Cost is wall-clock ms per simulated second per trajectory
(best of --repeats rounds, each round timing PyBullet and every variant in turn, so that the
load of a shared machine hits all alike); "x PyBullet" is PyBullet's cost over the variant's (above 1: faster than
PyBullet); accuracy is the MOVi-A metrics against the dataset (PyBullet's own scenes, so
PyBullet's error is 0 by construction). One thread throughout.

    python benchmarks/bench_learned_vs_physics.py --run movi_a --data data/movi_a_4000
    python benchmarks/bench_learned_vs_physics.py --run RUN --data DIR --variants plain,free,free+bf16 --json out.json \
        --plot out.png
    python benchmarks/bench_learned_vs_physics.py --run movi_a --run movi_a_fast --data DIR \
        --variants free+bf16+compile,free+sym+bf16+compile
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent.parent), str(Path(__file__).resolve().parent)]

from bench_datagen import step_only  # noqa: E402
from datagen.scenes import sample_scene  # noqa: E402
from gns.checkpoint import checkpoint_of  # noqa: E402
from gns.evaluate import load_split, rollout_scenes  # noqa: E402
from gns.metrics import evaluate_scenes  # noqa: E402
from gns.symmetry import SYMMETRY_GROUPS  # noqa: E402
from gns.checkpoint import load_model, read_checkpoint  # noqa: E402

GROUPS = tuple(g for g in SYMMETRY_GROUPS if g != "d2")   # --symmetrize GROUP; "sym" is d2
KNOWN = ("plain", "free", "sleep", "bf16", "compile", "freeze", "sym", *GROUPS)


def clearance(part: str) -> float | None:
    """The height D of a variant part "clearD" (free flight's clearance), else None."""
    try:
        return float(part[5:]) if part.startswith("clear") and float(part[5:]) >= 0 else None
    except ValueError:
        return None


def parse_variants(text: str) -> list[tuple[str, set[str]]]:
    out = []
    for name in text.split(","):
        parts = set(name.strip().split("+"))
        unknown = {p for p in parts - set(KNOWN) if clearance(p) is None}
        if unknown:
            raise SystemExit(f"error: unknown variant part {sorted(unknown)[0]!r}; known: {', '.join(KNOWN)}, clearD")
        if any(clearance(p) is not None for p in parts) and "free" not in parts:
            raise SystemExit(f"error: variant {name.strip()!r}: clearD sets free flight's height, it needs free")
        groups = sorted(parts & {"sym", *GROUPS})
        if len(groups) > 1:
            raise SystemExit(f"error: variant {name.strip()!r} averages over {' and '.join(groups)}; one group a variant")
        out.append((name.strip(), parts))
    return out


def pybullet_specs(ds, scenes, split: str) -> tuple[dict, list]:
    """The scenes' PyBullet specs from the dataset's config and seed, checked against frame 0."""
    cfg, seed = ds.meta["config"], int(ds.meta["seed"])
    specs = [sample_scene(cfg, seed, split, int(sc.attrs["index"])) for sc in scenes]
    for spec, sc in zip(specs, scenes):
        start = np.array([o.position for o in spec.objects])
        if not np.allclose(start, sc.positions[0], atol=1e-9):
            raise SystemExit(f"error: scene {sc.attrs.get('scene_id')} does not start where the dataset's config "
                             "and seed put it; the dataset was not made by this datagen")
    return cfg, specs


class Roller:
    """Rolls the scenes out with one model in one variant: number type, compiled network
    (compiled once, reused), symmetrized steps and rollout options."""

    def __init__(self, sim, scenes, ds, batch: int):
        self.sim, self.scenes, self.ds, self.batch = sim, scenes, ds, batch

    def __call__(self, parts: set[str]):
        for model in (self.sim, *self.sim.members):
            model.set_speed("bf16" if "bf16" in parts else "none", bool(parts & {"compile", "freeze"}),
                            freeze="freeze" in parts)
        groups = [p for p in parts if p in GROUPS] + (["d2"] if "sym" in parts else [])
        # a clearance of None keeps the options' own, and here that is the floor clip
        with self.sim.using(symmetrize=groups[0] if groups else "none", batch=self.batch, free_flight="free" in parts,
                            free_clearance=next((clearance(p) for p in parts if clearance(p) is not None), None),
                            sleep="sleep" in parts):
            return rollout_scenes(self.sim, self.scenes, self.ds.meshes, self.ds.frame_rate, progress=False)


def timed_rounds(variants: list[tuple[str, Roller, set[str]]], specs, cfg, repeats: int) -> tuple[dict, dict, dict, dict]:
    """Warm every variant up (compiling, filling caches), then time rounds that alternate
    PyBullet and every variant, so that a change of the machine's load hits all alike. Returns
    the best seconds per name ("physics" for PyBullet), first-call seconds, predictions and
    object-step counts per variant."""
    first = {}
    for name, roll, parts in variants:
        t0 = time.perf_counter()
        roll(parts)
        first[name] = time.perf_counter() - t0
    best = {"physics": float("inf"), **{name: float("inf") for name, _, _ in variants}}
    preds, counts = {}, {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        for spec in specs:
            step_only(spec, cfg)
        best["physics"] = min(best["physics"], time.perf_counter() - t0)
        for name, roll, parts in variants:
            t0 = time.perf_counter()
            preds[name] = roll(parts)
            best[name] = min(best[name], time.perf_counter() - t0)
            counts[name] = dict(roll.sim.rollout_counts)
    return best, first, preds, counts


def result_rows(best, first, preds, counts, variants, scenes, ds, cfg) -> list[dict]:
    """One row for PyBullet and one a variant: cost per simulated second, ratio, errors."""
    physics_ms = 1e3 * best["physics"] / sum((sc.num_frames - 1) / ds.frame_rate for sc in scenes)
    simulated = sum((sc.num_frames - 3) / ds.frame_rate for sc in scenes)
    rows = [{"variant": f"PyBullet {cfg['physics']['rate']} Hz, {cfg['physics']['solver_iterations']} iterations",
             "ms_per_simulated_second": physics_ms, "x_pybullet": 1.0, "network_share_pct": None,
             "position_error_pct": 0.0, "rotation_error_deg": 0.0, "penetration_pct": None}]
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    for name, _, _ in variants:
        r = evaluate_scenes(preds[name], scenes, ds.meshes, floor_z=floor_z)
        ms = 1e3 * best[name] / simulated
        c = counts[name]
        rows.append({"variant": f"GNS {name}", "ms_per_simulated_second": ms, "x_pybullet": physics_ms / ms,
                     "network_share_pct": 100.0 * c["network"] / c["object_steps"],
                     "position_error_pct": r["position_error_pct"], "rotation_error_deg": r["rotation_error_deg"],
                     "penetration_pct": r["penetration_pct"], "first_call_seconds": first[name], "counts": c})
    return rows


def print_table(rows: list[dict]) -> None:
    print("| simulator | ms per simulated s | x PyBullet throughput | object-steps in the network | "
          "position % | rotation deg | penetration % |")
    print("|---|---|---|---|---|---|---|")
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for r in rows:
        print(f"| {r['variant']} | {r['ms_per_simulated_second']:.2f} | {r['x_pybullet']:.2f} | "
              f"{fmt(r['network_share_pct'], '.1f')}{'' if r['network_share_pct'] is None else '%'} | "
              f"{fmt(r['position_error_pct'], '.2f')} | {fmt(r['rotation_error_deg'], '.2f')} | "
              f"{fmt(r['penetration_pct'], '.3f')} |")


def pareto_front(xs: list[float], ys: list[float]) -> list[int]:
    """Indices of the points no other point beats on both axes (higher x, lower y), by x descending."""
    order = sorted(range(len(xs)), key=lambda i: (-xs[i], ys[i]))
    front, best = [], float("inf")
    for i in order:
        if ys[i] < best:
            front.append(i)
            best = ys[i]
    return front


def _short_names(runs: list[str]) -> list[str]:
    """Run names without the prefix they all share (gns_movi_a_...), each part of an ensemble too."""
    members = [[Path(m).name for m in r.split("+")] for r in runs]
    parts = [m for ms in members for m in ms]
    cut = len(os.path.commonprefix(parts)) if len(parts) > 1 else 0
    cut = parts[0][:cut].rfind("_") + 1 if cut else 0   # whole words only
    return ["+".join(m[cut:] for m in ms) for ms in members]


def plot_rows(rows: list[dict], runs: list[str], path: str) -> Path:
    """Throughput against PyBullet's (x axis, log) and position / rotation error (two panels):
    one colour per model, one marker per rollout option, the points no other beats on both axes
    joined (the trade's front) and named, PyBullet's throughput drawn as the line to reach.
    Lower right is better."""
    from matplotlib.lines import Line2D

    from gns.charts import label_points, log_x_axis
    from gns.plots import new_figure, save_figure
    fig = new_figure((11, 5.2))
    learned = [r for r in rows if r["variant"].startswith("GNS ")]
    model, option = [], []   # "GNS [RUN ]OPTIONS": the run is named only when there are several
    for r in learned:
        name = r["variant"][len("GNS "):]
        run = next((m for m in runs if name.startswith(f"{m} ")), None) if len(runs) > 1 else runs[0]
        model.append(run)
        option.append(name[len(run) + 1:] if len(runs) > 1 else name)
    options = list(dict.fromkeys(option))
    markers = "osD^v<>p*h"
    short = dict(zip(runs, _short_names(runs)))
    axes = fig.subplots(1, 2)
    for ax, key, what in zip(axes, ("position_error_pct", "rotation_error_deg"),
                             ("position error [% of size]", "rotation error [deg]")):
        xs, ys = [r["x_pybullet"] for r in learned], [r[key] for r in learned]
        for i, r in enumerate(learned):
            ax.scatter(xs[i], ys[i], color=f"C{runs.index(model[i]) % 10}", s=36, zorder=3,
                       marker=markers[options.index(option[i]) % len(markers)])
        front = pareto_front(xs, ys)
        fx, fy = [xs[i] for i in front], [ys[i] for i in front]
        ax.step(fx, fy, where="post", color="0.5", lw=0.9, zorder=1)
        ax.axvline(1.0, color="0.3", ls="--", lw=0.8)
        log_x_axis(ax, "x")
        ax.set_xlabel("throughput, x PyBullet (batched, one thread; right is faster)")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3, which="both")
        ax.margins(y=0.2)
        ax.set_xlim(min(xs + [1.0]) / 1.6, max(xs + [1.0]) * 1.6)
        tag = {o: f" ({k + 1})" if len(options) > 1 else "" for k, o in enumerate(options)}
        label_points(ax, fx, fy, [short[model[i]] + tag[option[i]] for i in front], fontsize=6.5)
    handles = [Line2D([], [], ls="", marker="o", color=f"C{k % 10}", label=short[r]) for k, r in enumerate(runs)]
    handles += [Line2D([], [], ls="", marker=markers[k % len(markers)], color="0.3",
                       label=f"({k + 1}) {o}" if len(options) > 1 else o) for k, o in enumerate(options)]
    handles += [Line2D([], [], color="0.5", lw=0.9, label="front: nothing faster and more accurate"),
                Line2D([], [], color="0.3", ls="--", lw=0.8, label="PyBullet's throughput")]
    fig.legend(handles=handles, fontsize=7, loc="lower center", ncol=min(4, len(handles)), frameon=False)
    fig.suptitle("learned rollouts against PyBullet on the same scenes (PyBullet's own error is 0)", fontsize=9)
    fig.tight_layout(rect=(0, 0.06 + 0.035 * ((len(handles) - 1) // 4), 1, 1))
    return save_figure(fig, path, dpi=130)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append",
                   help="run folder, checkpoint or shipped model name; A+B an ensemble (each step averages "
                        "A's and B's predictions, `gns eval --ensemble`); repeat to compare models in the same rounds")
    p.add_argument("--data", help="a datagen toss dataset (its config and seed remake the scenes)")
    p.add_argument("--split", default="test")
    p.add_argument("--limit", type=int, help="first N scenes only")
    p.add_argument("--batch", type=int, default=1024,
                   help="objects rolled out together (default 1024: MOVi-A's 400 test scenes in one batch)")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats, best taken (default 3)")
    p.add_argument("--variants", default="plain,free,bf16,free+bf16,compile,free+bf16+compile",
                   help="comma list of +-joined parts: " + ", ".join(KNOWN))
    p.add_argument("--json", help="also write the rows here")
    p.add_argument("--plot", help="also draw the rows here (PNG): throughput against position and rotation error")
    p.add_argument("--replot", metavar="JSON", help="only draw --plot from an earlier run's --json (no timing)")
    a = p.parse_args(argv)
    if a.replot:
        return replot(p, a)
    if not a.run or not a.data:
        p.error("--run and --data are required (or --replot JSON --plot PNG)")
    variants = parse_variants(a.variants)
    torch.set_num_threads(1)

    runs, splits = [], {}  # the split read once per frame rate, not once per model
    for run in a.run:
        first, *others = run.split("+")   # A+B: an ensemble, each step averaging A's and B's predictions
        saved = read_checkpoint(checkpoint_of(first))
        sim, _ = load_model(saved, "cpu")
        sim.eval()
        if others:
            try:
                sim.set_ensemble([load_model(read_checkpoint(checkpoint_of(o)), "cpu")[0].eval() for o in others])
            except ValueError as e:
                raise SystemExit(f"error: --run {run}: {e}") from None
        rate = saved["spec"]["frame_rate"]
        if rate not in splits:
            splits[rate] = load_split(a.data, a.split, a.limit, rate)
        ds, scenes = splits[rate]
        if ds.stride != 1:
            raise SystemExit(f"error: {run} steps at a stride of the data's frames; this benchmark compares "
                             "at the data's own rate")
        runs.append((run, Roller(sim, scenes, ds, a.batch)))
    # one model keeps the variant names short; several name theirs
    jobs = [(name if len(runs) == 1 else f"{run} {name}", roller, parts)
            for run, roller in runs for name, parts in variants]
    cfg, specs = pybullet_specs(ds, scenes, a.split)
    timings = timed_rounds(jobs, specs, cfg, a.repeats)
    rows = result_rows(*timings, jobs, scenes, ds, cfg)
    print(f"{len(scenes)} {a.split} scenes of {a.data} ({ds.frame_rate:g} fps), model {', '.join(a.run)}; "
          f"one thread, best of {a.repeats}; GNS scenes batched, {a.batch} objects a batch")
    print_table(rows)
    if a.json:
        Path(a.json).write_text(json.dumps({"run": a.run, "data": a.data, "split": a.split, "scenes": len(scenes),
                                            "repeats": a.repeats, "batch": a.batch, "rows": rows}, indent=2,
                                           default=float) + "\n")
    if a.plot:
        print(f"plot: {plot_rows(rows, a.run, a.plot)}")
    return 0


def replot(parser: argparse.ArgumentParser, a: argparse.Namespace) -> int:
    """--replot JSON --plot PNG: the figure of an earlier run, from its rows."""
    source = Path(a.replot)
    if not a.plot:
        parser.error("--replot needs --plot, the PNG to draw")
    if not source.is_file():
        parser.error(f"--replot {source}: no such file")
    saved = json.loads(source.read_text())
    print(f"plot: {plot_rows(saved['rows'], saved['run'], a.plot)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
