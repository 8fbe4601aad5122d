"""Speed against accuracy, measured: PyBullet's knobs and the GNS's knobs on the same scenes.

    python -m pipelines.speed_accuracy --preset quick [--out runs/speed_accuracy_quick]

Physics side: the same test scenes simulated at several physics rates (sub-steps per recorded
frame) and solver iteration counts, timed (wall seconds per simulated second per trajectory)
and scored against a fine reference (10x the finest rate, 4x the iterations) with the metrics
of docs/metrics.md. GNS side: models trained at several message-passing depths (L x K),
latent sizes and frame strides (training and rolling out at every 1st, 2nd, 4th frame of data
recorded at a finer rate), timed single and batched, scored against the same reference.
Output: results.json, table.md and pareto.png (error against cost, log scale).
Finished stages are skipped on a rerun.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from datagen.scenes import load_config as scene_config
from datagen.scenes import sample_scene
from datagen.shards import Dataset
from datagen.toss import simulate
from gns.config import build_config
from gns.data import feature_spec
from gns.checkpoint import checkpoint_of
from gns.evaluate import load_split, rollout_scenes, split_diverged, write_json
from gns.metrics import METRICS, evaluate_scenes
from gns.simulator import LearnedSimulator
from gns.checkpoint import load_model, read_checkpoint
from plumbing import check_writable
from pipelines.common import CONFIGS, data_stage, guarded, say, train_stage

SHAPES = "scene.shapes=['beveled_cube', 'cylinder', 'sphere']"

# Scenes are scored at 12 fps (MOVi-A's rate); `fine` x 12 fps is the rate the reference and the
# sweep's training data are recorded at, so that strides 1 .. fine train GNS time steps of
# 1/(12 fine) .. 1/12 s. `train` holds the trained part of the sweep: each run is the model
# preset with one knob changed, trained for the same number of steps on the same scenes.
PRESETS = {
    "tiny": dict(scenes=2, frames=12, fine=2, rates=[120, 240], iterations=[10], reference=(1200, 200),
                 architectures=[(1, 1, 16)], batches=[1, 2], single_scenes=2,
                 train=dict(scenes=4, model="tiny", steps=20, strides=[1, 2], architectures=[(1, 1, 8)]),
                 compile=False),  # compiling every tiny model would cost more than the whole preset
    "quick": dict(scenes=40, frames=24, fine=4, rates=[60, 120, 240, 480, 960], iterations=[5, 10, 50],
                  reference=(9600, 200), architectures=[(1, 1, 64), (5, 1, 32), (5, 1, 64), (5, 1, 128), (10, 3, 128)],
                  batches=[1, 8, 40], single_scenes=8,
                  train=dict(scenes=400, model="cpu", steps=6000, strides=[1, 2, 4],
                             architectures=[(1, 1, 64), (5, 1, 32), (5, 1, 128)],
                             # bf16 where this CPU runs it faster (2.1x the steps/s of float32 on one
                             # with avx512_bf16, benchmarks/bench_train.py), float32 where it emulates it
                             sets=["train.autocast=auto", "train.compile=true"])),
}


def physics_point(cfg_sets: list[str], n: int, seed: int = 0) -> tuple[list, float]:
    """Simulate n test scenes with these settings; returns (scenes, wall seconds)."""
    cfg = scene_config(sets=cfg_sets)
    specs = [sample_scene(cfg, seed, "test", i) for i in range(n)]
    t0 = time.perf_counter()
    scenes = [simulate(s, cfg) for s in specs]
    return scenes, time.perf_counter() - t0


def fine_frames(p: dict) -> list[str]:
    """Scene settings recording p['frames'] frames at 12 fps as (frames - 1) fine + 1 frames at 12 fine fps."""
    return [f"scene.frame_rate={12 * p['fine']}", f"scene.frames={(p['frames'] - 1) * p['fine'] + 1}"]


def reference(p: dict, out: Path) -> Dataset:
    """The fine reference: the test scenes at 10x the finest rate, recorded at 12 x fine fps
    (read with stride `fine`, it is the 12 fps truth)."""
    rate, iters = p["reference"]
    sets = [SHAPES, *fine_frames(p), f"physics.rate={rate}", f"physics.solver_iterations={iters}"]
    say(f"reference: {p['scenes']} scenes at {rate} Hz, {iters} solver iterations")
    return data_stage(out, sets, {"test": p["scenes"]}, seed=0, workers=2)


def physics_sweep(p: dict, ref: Dataset) -> list[dict]:
    base = [SHAPES, "scene.frame_rate=12", f"scene.frames={p['frames']}"]
    true = Dataset(ref.root, stride=p["fine"]).load("test")
    simulated = p["scenes"] * (p["frames"] - 1) / 12.0
    rows = []
    for r in p["rates"]:
        for it in p["iterations"]:
            scenes, seconds = physics_point(base + [f"physics.rate={r}", f"physics.solver_iterations={it}"], p["scenes"])
            res = evaluate_scenes(scenes, true, ref.meshes, floor_z=0.0)
            rows.append({"family": "pybullet", "label": f"{r} Hz, {it} it", "physics_rate": r, "solver_iterations": it,
                         "batch": 1, "seconds_per_simulated_second": seconds / simulated,
                         **{k: res[k] for k in METRICS}})
            say(f"physics: {rows[-1]['label']}: {rows[-1]['position_error_pct']:.2f}% position, "
                f"{rows[-1]['seconds_per_simulated_second'] * 1e3:.2f} ms per simulated s")
    return rows


def _timed_rollout(sim, scenes, ds: Dataset, batch: int) -> float:
    """Wall seconds per simulated second per trajectory, rolling out `batch` scenes at a time."""
    t0 = time.perf_counter()
    for k in range(0, len(scenes), batch):
        with sim.using(batch=batch):
            rollout_scenes(sim, scenes[k:k + batch], ds.meshes, ds.frame_rate, progress=False)
    seconds = time.perf_counter() - t0
    return seconds / sum((sc.num_frames - 3) / ds.frame_rate for sc in scenes)


def gns_speed(p: dict, ref: Dataset) -> list[dict]:
    """Rollout cost of each architecture and batch size. The cost of a forward pass does not
    depend on the weights, so untrained models time exactly what trained ones would."""
    torch.set_num_threads(1)
    ref = Dataset(ref.root, stride=p["fine"])
    scenes = ref.load("test")
    spec = feature_spec(ref, scenes)
    rows = []
    for L, K, latent in p["architectures"]:
        cfg = build_config(overrides=[f"model.message_passing_steps={L}", f"model.processor_repeats={K}",
                                      f"model.latent_size={latent}", f"model.hidden_size={latent}"])
        sim = LearnedSimulator(cfg.model, cfg.features, spec).eval()
        for batch in p["batches"]:
            cost = _timed_rollout(sim, scenes[:max(batch, p["single_scenes"])], ref, batch)
            rows.append({"family": "gns speed", "label": f"L{L}xK{K}, latent {latent}, batch {batch}", "L": L, "K": K,
                         "latent": latent, "batch": batch, "seconds_per_simulated_second": cost})
            say(f"gns speed: {rows[-1]['label']}: {cost * 1e3:.2f} ms per simulated s")
    return rows


def sweep_runs(p: dict, out: Path) -> list[tuple[str, Path]]:
    """Train the sweep's runs (each skipped once trained): the model preset at every frame
    stride, and the other architectures at the 12 fps stride. Returns (knob, run folder)."""
    t = p["train"]
    sets = [SHAPES, *fine_frames(p)]
    data = data_stage(out / "train_data", sets, {"train": t["scenes"], "valid": max(2, t["scenes"] // 20)},
                      seed=1, workers=2)
    base = build_config(path=CONFIGS / f"gns_{t['model']}.toml").model
    runs = []
    for stride in t["strides"]:
        runs.append(("frame stride", out / "runs" / f"stride{stride}", [f"features.frame_stride={stride}"]))
    for L, K, latent in t["architectures"]:
        runs.append(("architecture", out / "runs" / f"L{L}K{K}_latent{latent}",
                     [f"features.frame_stride={p['fine']}", f"model.message_passing_steps={L}",
                      f"model.processor_repeats={K}", f"model.latent_size={latent}", f"model.hidden_size={latent}"]))
    say(f"sweep: {len(runs)} runs of {t['steps']} steps, base model L{base.message_passing_steps}"
        f"xK{base.processor_repeats} latent {base.latent_size}")
    for _, run, overrides in runs:
        train_stage(data.root, run, t["model"], [f"train.steps={t['steps']}", *t.get("sets", []), *overrides])
    return [(knob, run) for knob, run, _ in runs]


# the fast rollout options: gns eval --free-flight --autocast auto --compile (and --symmetrize);
# auto: bf16 where it measures faster on this machine (gns.speedups), else float32; each row says which
FAST = "free flight + auto precision + compile"
FAST_SYM = FAST + " + symmetrized"
MODES = {None: "gns batched", "fast": "gns fast", "fast sym": "gns fast sym"}


def _rollout_all(sim, scenes, ds, batch: int, count: int, mode: str | None = None,
                 compile: bool = True) -> tuple[list, float, str]:
    """Roll out the first `count` scenes `batch` at a time; (predictions, seconds per simulated
    second per trajectory, the network's precision: "float32" or "bf16"). mode "fast": free flight, the network compiled and under bf16 autocast
    where bf16 measures faster here (FAST); "fast sym": also symmetrized (FAST_SYM), the most
    accurate and 4x the network."""
    fast = mode is not None
    sim.set_speed("auto" if fast else "none", compile=fast and compile)
    t0 = time.perf_counter()
    pred = []
    with sim.using(batch=batch, free_flight=fast, symmetrize="d2" if mode == "fast sym" else "none"):
        for k in range(0, count, batch):
            pred += rollout_scenes(sim, scenes[k:k + batch], ds.meshes, ds.frame_rate, progress=False)
    cost = (time.perf_counter() - t0) / sum((sc.num_frames - 3) / ds.frame_rate for sc in scenes[:len(pred)])
    precision = "bf16" if sim.autocast_used == "bf16" else "float32"
    sim.set_speed()
    return pred, cost, precision


def gns_accuracy(runs: list[tuple[str, Path]], ref: Dataset, p: dict) -> list[dict]:
    """Trained runs scored against the fine reference at 12 fps, timed single and batched, and
    batched again with FAST and FAST_SYM where the model knows gravity.

    A run at a finer time step rolls out on the reference read at its own rate and is scored
    on every (12 fine / its rate)-th frame, so every run is judged at the same instants."""
    torch.set_num_threads(1)
    truth = Dataset(ref.root, stride=p["fine"])
    true = truth.load("test")
    rows = []
    for knob, run in runs:
        saved = read_checkpoint(checkpoint_of(run))
        sim, cfg = load_model(saved)
        ds, scenes = load_split(ref.root, "test", None, saved["spec"]["frame_rate"])
        keep = round(ds.frame_rate / truth.frame_rate)
        m = cfg.model
        modes = [(1, None), (len(scenes), None)]
        if sim.gravity_per_frame is not None:
            modes += [(len(scenes), "fast"), (len(scenes), "fast sym")]
        for batch, mode in modes:
            # warm-up (compiling, at the batch's size): first-call costs are not the rollout's
            _rollout_all(sim, scenes, ds, batch, batch, mode, p.get("compile", True))
            pred, cost, precision = _rollout_all(sim, scenes, ds, batch, len(scenes) if batch > 1 else p["single_scenes"], mode,
                                      p.get("compile", True))
            res = {}
            if batch > 1:  # diverged rollouts are counted, not averaged in
                kept, kept_true, diverged = split_diverged([sc.every(keep) for sc in pred], true)
                res = {**evaluate_scenes(kept, kept_true, ref.meshes, floor_z=0.0), "diverged": len(diverged)}
            counts = sim.rollout_counts
            rows.append({"family": "gns" if batch == 1 else MODES[mode], "knob": knob,
                         "label": f"{run_name(run)}: L{m.message_passing_steps}xK{m.processor_repeats}, "
                                  f"latent {m.latent_size}"
                                  + f", dt {1e3 / ds.frame_rate:.1f} ms, batch {batch}"
                                  + {None: "", "fast": f", free flight + {precision} + compile",
                                     "fast sym": f", free flight + {precision} + compile + symmetrized"}[mode],
                         "run": str(run), "batch": batch, "L": m.message_passing_steps, "K": m.processor_repeats,
                         "latent": m.latent_size, "frame_rate": ds.frame_rate, "steps": int(saved["step"]),
                         "seconds_per_simulated_second": cost, "fast": mode is not None, "mode": mode,
                         "precision": precision,
                         "network_share_pct": 100.0 * counts["network"] / max(counts["object_steps"], 1), **res})
        single = next(r for r in rows[-len(modes):] if r["batch"] == 1)
        batched = next(r for r in rows[-len(modes):] if r["family"] == "gns batched")
        single.update({k: batched[k] for k in (*METRICS, "diverged")})  # single and batched: the same rollouts
        for r in rows[-len(modes):]:
            say(f"gns: {r['label']}: {r['position_error_pct']:.2f}% position, "
                f"{r['seconds_per_simulated_second'] * 1e3:.2f} ms")
    return rows


def run_name(run: str) -> str:
    """A run folder's name, or its parent's for a pipeline's `.../<name>/run`."""
    path = Path(run)
    return path.parent.name if path.name == "run" else path.name


def pareto_plot(rows: list[dict], path: Path) -> Path:
    """Error against cost, log-log. A run's variants (one scene at a time, batched, fast, fast
    symmetrized) are joined by a thin line and the run is named once, at its most accurate
    point; labels are placed where they overlap least (gns.charts.label_points)."""
    from gns.charts import label_points
    from gns.plots import new_figure, save_figure
    fig = new_figure((8.5, 5.6))
    ax = fig.subplots()
    cost = lambda r: r["seconds_per_simulated_second"]  # noqa: E731
    err = lambda r: r["position_error_pct"]  # noqa: E731
    labels = []   # (x, y, text)
    bullet = [r for r in rows if r["family"] == "pybullet"]
    for k, it in enumerate(sorted({r["solver_iterations"] for r in bullet})):
        pts = [r for r in bullet if r["solver_iterations"] == it]
        ax.plot([cost(r) for r in pts], [err(r) for r in pts],
                "o-", color=f"C{k}", alpha=0.8, label=f"PyBullet, {it} solver iterations")
        if k == 0:  # one label per physics rate is enough
            labels += [(cost(r), err(r), f"{r['physics_rate']} Hz") for r in pts]
    learned = [r for r in rows if r["family"].startswith("gns") and "position_error_pct" in r]
    for run in dict.fromkeys(r["run"] for r in learned):
        pts = sorted((r for r in learned if r["run"] == run), key=cost)
        ax.plot([cost(r) for r in pts], [err(r) for r in pts], "-", color="0.6", lw=0.6, zorder=1)
        best = min(pts, key=err)
        labels.append((cost(best), err(best), run_name(run)))
    for family, marker, color, what in (("gns", "s", "C5", "GNS, one scene at a time"),
                                        ("gns batched", "^", "C6", "GNS, all test scenes batched"),
                                        ("gns fast", "*", "C3", f"GNS batched, {FAST}"),
                                        ("gns fast sym", "P", "C1", f"GNS batched, {FAST_SYM}")):
        pts = [r for r in learned if r["family"] == family]
        if pts:
            ax.scatter([cost(r) for r in pts], [err(r) for r in pts], marker=marker, color=color, s=45,
                       label=what, zorder=2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ymax = max(err(r) for r in rows if "position_error_pct" in r)
    ax.set_ylim(top=ymax * 2)
    ax.set_xlabel("wall-clock seconds per simulated second per trajectory (1 CPU thread)")
    ax.set_ylabel("position error vs fine reference [% of size]")
    ax.set_title("speed against accuracy (lower left is better; a grey line joins one model's rollout options)")
    ax.title.set_fontsize(9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    if labels:
        xs, ys, texts = zip(*labels)
        label_points(ax, xs, ys, texts)
    return save_figure(fig, path, 130)


def table(rows: list[dict]) -> str:
    lines = ["| family | setting | ms per simulated s per trajectory | position % | rotation deg | penetration % |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        errs = " | ".join(f"{r[k]:.3g}" if k in r else "-" for k in METRICS)
        lines.append(f"| {r['family']} | {r['label']} | {r['seconds_per_simulated_second'] * 1e3:.3g} | {errs} |")
    return "\n".join(lines)


def throughput_ratio(rows: list[dict]) -> str:
    """GNS batched rollout throughput against PyBullet at the data's own settings (240 Hz, 50
    iterations), for the GNS at the same 12 fps step: the sweep's base model (L5 K1 latent 64)
    if trained, else the first 12 fps run; the most accurate 12 fps run; every FAST and FAST_SYM
    rollout of it and of the given runs; and last, the most accurate GNS rollout of all."""
    bullet = [r for r in rows if r["family"] == "pybullet" and r["physics_rate"] == 240 and r["solver_iterations"] == 50]
    at12 = [r for r in rows if abs(r.get("frame_rate", 12.0) - 12.0) < 1e-9]
    gns = [r for r in at12 if r["family"] == "gns batched"]
    gns.sort(key=lambda r: (r.get("knob") != "frame stride", r.get("knob") == "given"))
    if not bullet or not gns:
        return ""
    b = bullet[0]["seconds_per_simulated_second"]
    def option(r) -> str:
        """The rollout options of a row, with the precision its fast mode measured and took."""
        fast = {"gns fast": FAST, "gns fast sym": FAST_SYM}.get(r["family"])
        return "" if fast is None else ", " + fast.replace("auto precision", r.get("precision", "auto precision"))

    def line(r, what=""):
        g = r["seconds_per_simulated_second"]
        return (f"{what}{run_name(r['run'])} at 12 fps{option(r)}: {b / g:.2f}x "
                f"({g * 1e3:.3g} vs {b * 1e3:.3g} ms per simulated second per trajectory, "
                f"{r['position_error_pct']:.3g}% position)")
    lines = ["GNS batched rollout throughput / PyBullet (240 Hz, 50 iterations, one scene a process):", line(gns[0])]
    best = min(gns, key=lambda r: r["position_error_pct"])
    lines.append(line(best))
    fast_families = ("gns fast", "gns fast sym")
    lines += [line(r) for r in at12 if r["family"] in fast_families and (r["run"] == best["run"] or r.get("knob") == "given")]
    scored = [r for r in at12 if r["family"] in ("gns batched", *fast_families) and "position_error_pct" in r]
    lines.append(line(min(scored, key=lambda r: r["position_error_pct"]), "at the best accuracy of any GNS rollout: "))
    return "\n".join(dict.fromkeys(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.speed_accuracy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="quick")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--replot", action="store_true", help="only redraw table and plot from results.json")
    ap.add_argument("--runs", type=Path, nargs="*", default=[],
                    help="more trained run folders to score against the fine reference (e.g. runs/movi_a_small/run)")
    ap.add_argument("--no-train", action="store_true", help="skip the trained sweep (frame strides, architectures)")
    a = ap.parse_args(argv)
    p = PRESETS[a.preset]
    out = a.out or Path("runs") / f"speed_accuracy_{a.preset}"
    return guarded(lambda: run(a, p, out))


def run(a: argparse.Namespace, p: dict, out: Path) -> None:
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    if a.replot:
        saved = json.loads((out / "results.json").read_text())
        rows = saved["rows"]
        saved["throughput_ratio"] = ratio = throughput_ratio(rows)
        write_json(out / "results.json", saved)
        (out / "table.md").write_text(table(rows) + "\n\n" + ratio + "\n")
        pareto_plot(rows, out / "pareto.png")
        print(table(rows))
        print(ratio)
        return
    ref = reference(p, out / "reference")
    trained = [] if a.no_train else sweep_runs(p, out)
    rows = physics_sweep(p, ref) + gns_speed(p, ref) + gns_accuracy(trained + [("given", r) for r in a.runs], ref, p)
    ratio = throughput_ratio(rows)
    write_json(out / "results.json", {"preset": a.preset, "settings": p, "rows": rows, "throughput_ratio": ratio})
    (out / "table.md").write_text(table(rows) + "\n\n" + ratio + "\n")
    pareto_plot(rows, out / "pareto.png")
    print(table(rows))
    print(ratio)


if __name__ == "__main__":
    sys.exit(main())
