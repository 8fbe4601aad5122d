"""An ensemble GNS on few real cube tosses, against the MuJoCo identified on the same tosses.

    python -m pipelines.real_cubes_ensemble --src DATA [--preset accuracy|tiny] [--out DIR] [--export DIR]

With 16 training tosses one recipe's seeds differ by up to 2 points of position: variance that
an average removes. On the split of pipelines/real_cubes.py (seed 2022, 96 test and 32
validation tosses), the pipeline trains `seeds` runs of two recipes on the same N tosses:
`real`, the 16-toss recipe of docs/accuracy.md (time step of 8 frames, windows at every phase,
mirror and body-frame augmentation, the signed floor distance clipped at 1.5), and `mujoco`, the
same on tosses of the MuJoCo identified on those N tosses plus the real ones repeated
(pipelines/engine_pretrain.py). Every member and the ensembles of each recipe and of all runs
(`gns eval --ensemble`: each step averages the members' predictions) are scored on the test and
validation tosses, symmetrized, at every recorded frame, beside the identified MuJoCo.
Stages are skipped on a rerun when done. Writes report.md and results.json; with --export, the
members as small files named gns_real_cubes_n<N>_e_<recipe><seed>.pt.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from plumbing.errors import DataError
from gns.evaluate import evaluate_run, write_json
from gns.checkpoint import export_model
from pipelines.common import Costs, done, guarded, say, train_stage, trained_step
from pipelines.engine_pretrain import synthetic_stage
from pipelines.real_cubes_baselines import available_engines, baselines_stage
from pipelines.real_cubes_data import (duplicate_groups, import_stage, make_split, read_tosses, real_cubes_parser,
                                      training_ids)
from pipelines.real_cubes_report import metric_cells, summary

# The 16-toss recipe of docs/accuracy.md (session 4's floor feature), as the shipped members were trained.
RECIPE = ("train.threads=1", "train.batch_size=32", "train.lr_init=1e-3", "augment.noise_std=0.001",
          "features.frame_stride=8", "train.all_phases=true", "augment.mirror=true", "augment.body_symmetry=true",
          "features.floor_clip=1.5", "features.floor_signed=true")
SPLITS = ("test", "valid")


@dataclass(frozen=True)
class Preset:
    tosses: int
    test: int
    valid: int
    seeds: int
    steps: int
    synthetic: int           # tosses of the identified MuJoCo
    real_copies: int         # copies of each real toss beside them
    model: str = "cpu"
    fit_budget: int = 120
    fit_tosses: int | None = 64


PRESETS = {
    "tiny": Preset(tosses=2, test=1, valid=0, seeds=2, steps=30, synthetic=4, real_copies=2, model="tiny",
                   fit_budget=3, fit_tosses=None),
    # 10k steps: ~3.6 minutes a run alone on one core, 8 runs; the MuJoCo fit ~20 s
    "accuracy": Preset(tosses=16, test=96, valid=32, seeds=4, steps=10000, synthetic=2000, real_copies=40),
}


def eval_stage(path: Path, runs: list[Path], data: Path, split: str) -> dict:
    """Symmetrized rollouts at the data rate of runs[0], with runs[1:] as its ensemble; skipped
    when made from these runs at their present steps."""
    members, steps = [str(r) for r in runs[1:]], [trained_step(r) for r in runs]
    results = done(path, runs[0] / "latest.pt")
    if results is not None and results.get("ensemble") == members and results.get("member_steps") == steps:
        return results
    results, *_ = evaluate_run(runs[0], data, split, symmetrize=True, at_data_rate=True, progress=False,
                               ensemble=members)
    results.update(checkpoint_step=steps[0], member_steps=steps)
    write_json(path, results)
    return results


def run(preset: str, src: Path, out: Path, export: Path | None = None) -> dict:
    p = PRESETS[preset]
    if not Path(src).is_dir():
        raise DataError(f"source folder does not exist: {src}")
    if "mujoco" not in available_engines():
        raise DataError("the mujoco recipe needs MuJoCo: pip install -e '.[mujoco]'")
    split = make_split(duplicate_groups(read_tosses(Path(src))), p.test, p.valid)
    ids = training_ids(split, p.tosses, 0)
    out.mkdir(parents=True, exist_ok=True)
    splits = [s for s in SPLITS if split[s]]
    data = {s: import_stage(Path(src), out / "data" / s, {s: split[s]}) for s in splits}
    train = import_stage(Path(src), out / "data" / f"train_n{p.tosses}_s0",
                         {"train": ids, **({"valid": split["valid"]} if split["valid"] else {})})
    base = baselines_stage(out / "baseline", {(p.tosses, 0): (train, ids)}, data["test"], ["mujoco"],
                           p.fit_budget, p.fit_tosses, Costs(out / "costs.json"))
    params = base["fits"]["mujoco"][f"n{p.tosses}_s0"]["params"]
    mixed = synthetic_stage(out / "data" / f"mujoco_n{p.tosses}_s0", train, "mujoco", params, p.synthetic, 0,
                            p.real_copies)
    runs = {"real": [], "mujoco": []}
    for seed in range(p.seeds):
        for recipe, dataset in (("real", train), ("mujoco", mixed.root)):
            run_dir = out / "runs" / f"{recipe}_s{seed}"
            train_stage(dataset, run_dir, p.model, [*RECIPE, f"train.steps={p.steps}",
                                                    f"train.lr_decay_steps={max(1, p.steps // 3)}",
                                                    f"train.seed={seed}"])
            runs[recipe].append(run_dir)
    groups = {f"{recipe} seed {s}": [r] for recipe in runs for s, r in enumerate(runs[recipe])}
    groups.update({"ensemble of the real runs": runs["real"], "ensemble of the mujoco runs": runs["mujoco"],
                   "ensemble of all runs": runs["mujoco"] + runs["real"]})
    rows = {}
    for name, members in groups.items():
        tag = name.replace(" ", "_")
        rows[name] = {s: summary(eval_stage(out / "eval" / f"{tag}.{s}.json", members, data[s], s)) for s in splits}
        say(f"{name}: test {rows[name]['test']['position_error_pct']:.2f}% "
            f"{rows[name]['test']['rotation_error_deg']:.2f} deg")
    engine = {"test": summary(base["evals"]["mujoco"][f"n{p.tosses}_s0"])}
    results = {"preset": preset, "src": str(src), "tosses": p.tosses, "seeds": p.seeds, "steps": p.steps,
               "synthetic": p.synthetic, "real_copies": p.real_copies, "rows": rows, "mujoco": engine}
    write_json(out / "results.json", results)
    report(out, results)
    if export is not None:
        for recipe, members in runs.items():
            for s, r in enumerate(members):
                export_model(r / "latest.pt", export / f"gns_real_cubes_n{p.tosses}_e_{recipe}{s}.pt", overwrite=True)
    say(f"report: {out / 'report.md'}")
    return results


def report(out: Path, results: dict) -> Path:
    lines = [f"# Real cube tosses: an ensemble GNS at {results['tosses']} tosses (preset `{results['preset']}`)", "",
             f"Made by `python -m pipelines.real_cubes_ensemble --src {results['src']} --preset {results['preset']}`. "
             f"{results['seeds']} seeds of each recipe, {results['steps']} steps; `mujoco`: {results['synthetic']} "
             f"tosses of the identified MuJoCo + the real ones x{results['real_copies']}. Symmetrized, every "
             "recorded frame (docs/metrics.md).", "",
             "| model | test position % | rotation deg | penetration % | valid position % | rotation deg | penetration % |",
             "|---|---|---|---|---|---|---|"]
    for name, row in results["rows"].items():
        lines.append(f"| {name} | {metric_cells(row['test'])} | {metric_cells(row.get('valid'))} |")
    lines.append(f"| MuJoCo identified on the same tosses | {metric_cells(results['mujoco']['test'])} | | | |")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv=None) -> int:
    ap = real_cubes_parser("real_cubes_ensemble", __doc__, PRESETS, "accuracy", out="real_cubes_ensemble")
    ap.add_argument("--export", type=Path, help="also write the trained members here (gns export)")
    a = ap.parse_args(argv)
    out = a.out or Path("runs") / f"real_cubes_ensemble_{a.preset}"
    return guarded(lambda: run(a.preset, a.src, out, a.export))


if __name__ == "__main__":
    sys.exit(main())
