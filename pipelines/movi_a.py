"""The paper's MOVi-A experiment: generate, train, score beside the zoo's model, PyBullet and the paper.

    python -m pipelines.movi_a --preset small [--out runs/movi_a_small]

Single-object tosses of the three MOVi-A shapes (beveled cube, cylinder, sphere) x 2 sizes x
2 materials: the preset's model is trained on them and rolled out from the first 3 frames of
held-out test scenes with shape matching. On the same test scenes, one report (report.md,
results.json, plots/) sets it beside
  - the zoo's MOVi-A model (ZOO_MODEL, rolled out with the options it was scored with): never
    trained on these scenes (scenes are keyed by seed, split and index; it saw train scenes only);
  - PyBullet at coarser physics rates (PHYSICS_RATES), re-simulated from the same initial states
    and scored against the data, PyBullet at 240 Hz: what a cheaper exact simulator gives;
  - the paper's figures (Allen et al. 2022, MOVi-A: 14.6% position, 17.2 degrees, 0.016%);
each with its cost, measured in the same run on one thread. Rerunning continues where the last
run stopped: finished stages (data, training, each scoring) are skipped.

Presets:
  tiny         the test suite's: 8 training scenes of 12 frames, the tiny model, 40 steps (seconds)
  small        the main job: 1000 training scenes, the CPU model (L=5, K=1, latent 64), 12000 steps
               (~15 min on 2 cores, data and scoring included)
  multi_tiny   smoke test of several objects a scene (2-3), collision edges between them
  multi_small  400 training scenes of 3-6 objects, the CPU model, 8000 steps (~45 min); the report
               adds interpenetration between objects (% of size, against the truth's own)
  paper        9000 training scenes, the paper's model (L=10, K=3, latent 128), 1M steps: days on a
               CPU, documented, not run here
The zoo's model is trained on single objects (no collision edges): the multi-object presets
leave its row out. Models trained by a recipe (the zoo's) are made by pipelines/recipe.py.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

from plumbing import check_writable, DataError
from datagen.shards import Dataset
from gns.checkpoint import read_checkpoint
from gns.evaluate import evaluate_run, score_predictions, write_json
from gns.metrics import format_table, per_frame_curves
from gns.spec import RolloutOptions
from pipelines.common import data_stage, done, guarded, remove_output, say, train_stage

# The zoo's MOVi-A model and the rollout options it was scored with (its card's).
ZOO_MODEL = "movi_a"
ZOO_OPTIONS = dict(symmetrize="d1", free_flight=True, free_clearance=0.5)

PAPER = {"position_error_pct": 14.6, "rotation_error_deg": 17.2, "penetration_pct": 0.016}
SHAPES = "scene.shapes=['beveled_cube', 'cylinder', 'sphere']"
# Physics steps a second of the PyBullet rows; the data's own is 240 (configs/movi_a.toml).
PHYSICS_RATES = (60, 120, 240)
METRICS = tuple(PAPER)

# small: 12000 steps instead of the 20000 of the earlier small preset, so that the whole job
# keeps to ~15 minutes beside another job on a 2-core machine (~15-20 steps/s measured); the
# learning rate decays as fast per step (lr_decay_steps 15000 -> 9000), ending where 20000 did.
PRESETS = {
    "tiny": dict(counts={"train": 8, "valid": 2, "test": 4}, model="tiny", steps=40, scene=["scene.frames=12"],
                 zoo=True),
    "small": dict(counts={"train": 1000, "valid": 50, "test": 100}, model="cpu", steps=12000, scene=[],
                  sets=["train.lr_decay_steps=9000"], zoo=True),
    "multi_tiny": dict(counts={"train": 6, "valid": 2, "test": 2}, model="tiny", steps=30,
                       scene=["scene.frames=12", 'scene.objects="2-3"'], zoo=False),
    "multi_small": dict(counts={"train": 400, "valid": 20, "test": 40}, model="cpu", steps=8000,
                        scene=['scene.objects="3-6"'], zoo=False),
    "paper": dict(counts={"train": 9000, "valid": 500, "test": 500}, model="paper", steps=1_000_000, scene=[],
                  zoo=True),
}

# Everything run() writes into --out: --fresh deletes a folder holding only these.
OUTPUTS = {"data", "run", "scores", "results.json", "report.md", "plots"}


def run(preset: str, out: Path, workers: int, seed: int) -> dict:
    p = PRESETS[preset]
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    data = data_stage(out / "data", [SHAPES, *p["scene"]], p["counts"], seed, workers)
    ckpt = train_stage(data.root, out / "run", p["model"],
                       [f"train.steps={p['steps']}", f"train.seed={seed}", *p.get("sets", [])])
    import torch
    threads = torch.get_num_threads()
    torch.set_num_threads(1)   # every simulator's cost on one core, as PyBullet's
    try:
        model = score_model(out, data, ckpt, preset)
        zoo = score_zoo(out, data) if p["zoo"] else None
        physics = score_physics(out, data, p, seed)
    finally:
        torch.set_num_threads(threads)
    results = {**model, "preset": preset, "paper": PAPER, "zoo": zoo, "pybullet": physics,
               "table": table_rows(model, zoo, physics), "seeds": {"data": seed, "train": seed},
               "scene_counts": p["counts"], "commands": commands(preset, out, p, seed),
               "machine": machine()}
    write_json(out / "results.json", results)
    error_plot(out, data, model, zoo, physics)
    path = report(out, results)
    say(f"report: {path}")
    print(format_table(model))
    print(markdown_table(results["table"]))
    return results


def score_model(out: Path, data: Dataset, ckpt: Path, preset: str) -> dict:
    """The preset's model on the test split (its plots into OUT/plots), skipped once scored at this step."""
    path = out / "scores" / "model.json"
    results = done(path, ckpt)
    if results is not None:
        say("eval: the trained model's scores match its checkpoint, skipping")
        return results
    say("eval: rolling out the test split with the trained model")
    results, pred, true, ds = evaluate_run(ckpt, data.root, "test", plots_dir=out / "plots")
    saved = read_checkpoint(ckpt)
    m = saved["config"]["model"]
    results.update(checkpoint_step=int(saved["step"]), curves=_curves(pred, true, ds), load=os.getloadavg(), train={
                       "model": PRESETS[preset]["model"], "step": int(saved["step"]), "L": m["message_passing_steps"],
                       "K": m["processor_repeats"], "latent": m["latent_size"],
                       "parameters": sum(v.numel() for k, v in saved["model"].items() if "normalizer" not in k)})
    write_json(path, results)
    return results


def score_zoo(out: Path, data: Dataset) -> dict:
    """The zoo's model on the same test split with its scored options, skipped once scored on these data."""
    path = out / "scores" / "zoo.json"
    key = {"model": ZOO_MODEL, "rollout_options": RolloutOptions(**ZOO_OPTIONS).to_dict(),
           "data_fingerprint": data.fingerprint}
    saved = _read(path)
    if saved is not None and all(saved.get(k) == v for k, v in key.items()):
        say(f"eval: the zoo's {ZOO_MODEL} was scored on these scenes, skipping")
        return saved
    say(f"eval: rolling out the test split with the zoo's {ZOO_MODEL} ({RolloutOptions(**ZOO_OPTIONS).describe()})")
    # these options whole, not the card's on top (its autocast "auto" would make the row depend on the CPU)
    results, pred, true, ds = evaluate_run(ZOO_MODEL, data.root, "test", options=RolloutOptions(**ZOO_OPTIONS),
                                           progress=False)
    results.update(key, curves=_curves(pred, true, ds), load=os.getloadavg())
    results.pop("per_scene", None)
    write_json(path, results)
    return results


def score_physics(out: Path, data: Dataset, p: dict, seed: int) -> list[dict]:
    """PyBullet at each of PHYSICS_RATES from the test scenes' initial states (their config and
    seed), scored against the data; skipped once done on these data."""
    from pipelines.speed_accuracy import physics_point
    path = out / "scores" / "pybullet.json"
    saved = _read(path)
    if saved is not None and saved.get("rates") == list(PHYSICS_RATES) and \
            saved.get("data_fingerprint") == data.fingerprint:
        say("eval: PyBullet was re-simulated on these scenes, skipping")
        return saved["rows"]
    true = data.load("test")
    rows = []
    for rate in PHYSICS_RATES:
        say(f"eval: PyBullet at {rate} Hz on the {len(true)} test scenes")
        pred, seconds = physics_point([SHAPES, *p["scene"], f"physics.rate={rate}"], len(true), seed)
        for a, b in zip(pred, true, strict=True):
            if a.attrs.get("scene_id") != b.attrs.get("scene_id") or \
                    abs(a.positions[0] - b.positions[0]).max() > 1e-9:
                raise DataError(f"{data.root}: test scene {b.attrs.get('scene_id')} does not start where its "
                                "config and seed put it; regenerate the data (--fresh)")
        r = score_predictions(pred, true, data, seconds)
        # PyBullet simulates from frame 0, every frame but the first
        simulated = sum((sc.num_frames - 1) / data.frame_rate for sc in true)
        rows.append({"rate": rate, **{k: r[k] for k in (*METRICS, "true_penetration_pct", "num_scenes")},
                     **({"interpenetration_pct": r["interpenetration_pct"]} if "interpenetration_pct" in r else {}),
                     "rollout_seconds": seconds, "wall_seconds_per_simulated_second": seconds / simulated,
                     "curves": _curves(pred, true, data), "load": os.getloadavg()})
    write_json(path, {"rates": list(PHYSICS_RATES), "data_fingerprint": data.fingerprint, "rows": rows})
    return rows


def _curves(pred: list, true: list, ds: Dataset) -> dict:
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    curves = per_frame_curves(pred, true, ds.meshes, floor_z)
    return {k: [float(x) for x in v] for k, v in curves.items() if k in (*METRICS, "true_penetration_pct")}


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):   # missing, or torn by a crash mid-write: the stage runs again
        return None


def table_rows(model: dict, zoo: dict | None, physics: list[dict]) -> list[dict]:
    """One row a simulator: its scores and what its rollouts of the test split cost."""
    def row(name, r, options=""):
        return {"simulator": name, **{k: r[k] for k in METRICS}, "rollout_seconds": r["rollout_seconds"],
                "ms_per_simulated_second": 1e3 * r["wall_seconds_per_simulated_second"], "options": options}
    rows = [row(f"this run's model ({model['train']['model']} preset, {model['train']['step']} steps)", model,
                RolloutOptions().describe() or "defaults")]
    if zoo is not None:
        rows.append(row(f"zoo `{ZOO_MODEL}`", zoo, RolloutOptions(**ZOO_OPTIONS).describe()))
    for r in physics:
        rows.append(row(f"PyBullet {r['rate']} Hz" + (" (the data's own rate)" if r["rate"] == 240 else ""), r,
                        "same solver as the data, 50 iterations"))
    rows.append({"simulator": "paper (Allen et al. 2022, MOVi-A)", **PAPER, "rollout_seconds": None,
                 "ms_per_simulated_second": None, "options": "L=10, K=3, 1M steps on MOVi-A"})
    return rows


def markdown_table(rows: list[dict]) -> str:
    fmt = lambda v, f=".3g": "-" if v is None else format(v, f)  # noqa: E731
    lines = ["| simulator | position % | rotation deg | penetration % | ms per simulated s | rollouts, s | options |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['simulator']} | {fmt(r['position_error_pct'])} | {fmt(r['rotation_error_deg'])} | "
                     f"{fmt(r['penetration_pct'])} | {fmt(r['ms_per_simulated_second'])} | "
                     f"{fmt(r['rollout_seconds'], '.2f')} | {r['options']} |")
    return "\n".join(lines)


def error_plot(out: Path, data: Dataset, model: dict, zoo: dict | None, physics: list[dict]) -> Path:
    """Error against time of this run's model, the zoo's and the coarsest PyBullet, one figure."""
    from gns.plots import plot_error_vs_time
    import numpy as np
    curves = {"this run's model": model["curves"]}
    if zoo is not None:
        curves[f"zoo {ZOO_MODEL}"] = zoo["curves"]
    coarse = min(physics, key=lambda r: r["rate"])
    curves[f"PyBullet {coarse['rate']} Hz"] = coarse["curves"]
    arrays = {name: {k: np.asarray(v) for k, v in c.items()} for name, c in curves.items()}
    return plot_error_vs_time(arrays, out / "plots" / "error_vs_time.png", dt=1.0 / data.frame_rate,
                              title="rollout error against time on the same test scenes (shaded: given frames)")


def commands(preset: str, out: Path, p: dict, seed: int) -> list[str]:
    """This run's command and the `datagen` / `gns` commands that do its stages one by one."""
    c = p["counts"]
    toss = (f"datagen toss --shapes beveled_cube,cylinder,sphere --scenes {c['train']} --valid {c['valid']} "
            f"--test {c['test']} --seed {seed} --out {out}/data")
    for s in p["scene"]:
        key, value = s.split("=", 1)
        toss += {"scene.frames": f" --frames {value}", "scene.objects": f" --objects {value.strip(chr(34))}"}[key]
    sets = " ".join([f"train.seed={seed}", *p.get("sets", [])])
    lines = [f"python -m pipelines.movi_a --preset {preset} --out {out} --seed {seed}", toss,
             f"gns train --data {out}/data --out {out}/run --config gns_{p['model']} --steps {p['steps']} --set {sets}",
             f"gns eval --run {out}/run --data {out}/data --split test"]
    if p["zoo"]:
        lines.append(f"gns eval --run {ZOO_MODEL} --data {out}/data --split test {RolloutOptions(**ZOO_OPTIONS).describe()}")
    return lines


def machine() -> dict:
    from gns.speedups import cpu_info
    return {**cpu_info(), "load_at_report": os.getloadavg(), "python": platform.python_version()}


def report(out: Path, results: dict) -> Path:
    model, zoo, m = results, results["zoo"], results["machine"]
    multi = "interpenetration_pct" in model
    lines = [f"# MOVi-A-style evaluation, preset `{results['preset']}`", "",
             f"{model['num_scenes']} held-out {'multi' if multi else 'single'}-object test scenes, every simulator on "
             "the same ones. The learned models roll out from the first 3 frames of each scene; PyBullet re-simulates "
             "each from its initial state (the scene's config and seed); all are scored against the data (PyBullet, "
             "240 Hz) with the metrics of docs/metrics.md, averaged over all frames, then over objects.", "",
             markdown_table(results["table"]), "",
             f"Cost: wall clock of the rollouts of all {model['num_scenes']} test scenes on one thread (the learned "
             "models batched, PyBullet one scene at a time with a fresh world each, as the data were made), and per "
             "simulated second of one scene (the learned models: of the frames they predict). The paper's row has no cost measured here.", "",
             f"Ground truth's own penetration: {model['true_penetration_pct']:.3g}% (the metric's floor)."]
    if multi:
        lines += ["", f"Interpenetration between objects (this run's model): {model['interpenetration_pct']:.3g}% of "
                      f"size, averaged over frames and {model['num_object_pairs']} object pairs; the ground truth's "
                      f"own: {model['true_interpenetration_pct']:.3g}%. At each pair's deepest frame: "
                      f"{model['interpenetration_max_pct']:.3g}% (truth {model['true_interpenetration_max_pct']:.3g}%); "
                      f"pairs deeper than 10% at some frame: {model['pairs_passing_through_pct']:.3g}% "
                      f"(truth {model['true_pairs_passing_through_pct']:.3g}%)."]
    t = model["train"]
    lines += ["", "## What ran", "",
              f"- Scenes: {', '.join(f'{n} {s}' for s, n in results['scene_counts'].items())} (data seed "
              f"{results['seeds']['data']}; each scene keyed by seed, split and index). "
              + ("The zoo's model was trained on train-split scenes (seed 0 of `datagen toss --shapes "
                 "beveled_cube,cylinder,sphere`), never on test-split ones." if zoo else ""),
              f"- This run's model: {t['model']} preset, {t['step']} training steps (training seed "
              f"{results['seeds']['train']}; {t['parameters']} parameters, L={t['L']}, K={t['K']}, latent {t['latent']}). "
              "The paper trains L=10, K=3 for up to 1M steps on far more data.",
              f"- rollout_options, this run's model: `{model['rollout_options']}`"]
    if zoo:
        lines.append(f"- rollout_options, zoo `{zoo['model']}`: `{zoo['rollout_options']}`")
    features = ", ".join(m.get("features") or []) or "none named"
    lines += [f"- Machine: {m['cpu']}, {m['cores']} cores (features: {features}); load average (1, 5, 15 min) while scoring: this run's model "
              f"{_load(model)}" + (f", zoo {_load(zoo)}" if zoo else "") + ", PyBullet "
              + ", ".join(f"{r['rate']} Hz {_load(r)}" for r in results["pybullet"]) + f"; at the report {_load(m, 'load_at_report')}.",
              "- Commands (the first runs all; the others are its stages one by one):", "", "```",
              *results["commands"], "```", "",
              "## This run's model, in detail", "", "```", format_table(model), "```", "",
              "## Plots", "", "![error against time](plots/error_vs_time.png)", "",
              "![median scene](plots/trajectory_median.png)", "", "![worst scene](plots/trajectory_worst.png)", "",
              "![best scene](plots/trajectory_best.png)", "", "Animation of the worst scene: `plots/rollout_worst.gif`."]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _load(r: dict, key: str = "load") -> str:
    return "/".join(f"{x:.2f}" for x in r[key])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.movi_a", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=list(PRESETS), default="small")
    ap.add_argument("--out", type=Path, help="output folder (default runs/movi_a_<preset>)")
    ap.add_argument("--workers", type=int, default=2, help="data generation processes")
    ap.add_argument("--seed", type=int, default=0, help="data and training seed")
    ap.add_argument("--fresh", action="store_true", help="delete the output folder first instead of resuming")
    a = ap.parse_args(argv)
    out = a.out or Path("runs") / f"movi_a_{a.preset}"

    def stages():
        if a.fresh:
            remove_output(out, OUTPUTS)
        t0 = time.perf_counter()
        run(a.preset, out, a.workers, a.seed)
        say(f"done in {time.perf_counter() - t0:.0f} s")
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
