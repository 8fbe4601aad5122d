"""The paper's real-cube experiments (Figures 4, 5, 7): a GNS against tuned PyBullet and MuJoCo.

    python -m pipelines.real_cubes --src DATA --preset quick [--out runs/real_cubes_quick] [--test-dir DIR]

DATA is the ContactNets `data/` folder (tosses_processed/N.pt, params_processed/experiment.json)
or a flat folder of N.pt files. The tosses are split once, with a fixed seed, into test, valid
and a training pool; rotated copies of a toss (the data hold 22 such pairs) always land on the
same side (pipelines/real_cubes_data.py). GNS models are trained on the first n tosses of the
pool for each size n (nested subsets; seed s > 0 reorders the pool and seeds the model), and
PyBullet's and MuJoCo's contact parameters are identified on the very same tosses
(pipelines/real_cubes_baselines.py; MuJoCo only if the [mujoco] extra is installed). Everything is rolled out from the
first 3 frames of the same test tosses and scored with the ContactNets metrics over the whole
toss (docs/metrics.md). At one size: ablations (absolute encoding, no shape matching at rollout,
one message-passing step, no rotation augmentation); at another: training with noise on the
cube's corners and on its tracked pose. --test-dir DIR scores every model and baseline on the
tosses of DIR as well (e.g. the ContactNets tosses kept out of the shared set).

Output in --out: report.md, results.json, plots/ (pipelines/real_cubes_report.py), split.json,
and the data/, runs/, eval/, baseline/ folders of the stages. Rerunning continues where the last run stopped: finished
stages are skipped. Presets (docs/results.md has their measured costs):
  tiny   the test suite's smoke run: sizes 1 and 2, a tiny model, 30 steps
  quick  sizes 8, 32, 128, one seed, the CPU model for 6000 steps; ablations at 128, noise at 32
  full   sizes 8 to 256, three seeds, 30000 steps; ablations and noise at 256
  zoo    the zoo's real_cubes itself (256 tosses, checked), its ablations and noise on its recipe
--workers N trains N GNS runs at a time.
"""
from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from plumbing import check_writable, DataError
from datagen.shards import Dataset
from gns.evaluate import evaluate_run, write_json
from gns.checkpoint import read_checkpoint
from pipelines.common import (Costs, done, guarded, in_processes, remove_output, say, train_stage, trained_step,
                              training_seconds, zoo_model_as_run)
from pipelines.real_cubes_baselines import available_engines, baselines_stage
from pipelines.real_cubes_data import (duplicate_groups, import_stage, make_split, overlaps, read_tosses,
                                      real_cubes_parser, training_ids)
from pipelines.real_cubes_report import fit_summary, make_plots, report, summary
from pipelines.recipe import load_recipe

# Everything run() writes into --out: --fresh deletes a folder holding only these.
OUTPUTS = {"split.json", "costs.json", "data", "runs", "eval", "baseline", "plots", "results.json", "report.md"}
ABLATIONS = {  # name: (label, training overrides); "nosm" reuses the full model's checkpoint
    "abs": ("absolute encoding", ["features.encoding=absolute"]),
    "1mp": ("1 message-passing step", ["model.message_passing_steps=1", "model.processor_repeats=1"]),
    "noaug": ("no rotation augmentation", ["augment.rotate=false"]),
}


@dataclass(frozen=True)
class Preset:
    test: int                      # test tosses (rotated copies kept together: may exceed by one)
    valid: int                     # validation tosses for the trainer's curves
    sizes: tuple[int, ...]         # training set sizes (Figure 4)
    seeds: tuple[int, ...]
    model: str                     # configs/gns_<model>.toml
    steps: int
    train: tuple[str, ...] = ()    # further training overrides
    baseline_budget: int = 120     # objective evaluations per baseline fit (each engine)
    baseline_tosses: int | None = 64   # fit on a seeded random subset of at most this many tosses
    ablation_size: int = 0         # one of sizes (Figure 5)
    noise_size: int = 0            # one of sizes (Figure 7)
    vertex_noise: tuple[float, ...] = ()   # std, fraction of the cube's size
    track_noise: tuple[float, ...] = ()    # std, fraction of the per-frame displacement
    plots: bool = True             # trajectory plots and GIFs of the largest size
    zoo: str | None = None         # a zoo model scored as the largest size's run when it is that run
                                   # (same tosses and settings; pipelines.common.zoo_model_as_run)


# Real-cube windows are 8-vertex graphs: the CPU model (latent 64, L=5) runs ~25 steps/s on one
# core with 32 graphs a step, 2.6x the graphs/s of 8 a step, and with lr 1e-3 it reached a
# third less error than batch 8 at 5e-4 in the same 7000 steps (128 tosses: 28% vs 42% position).
# The input-noise std is scaled to these data: MOVi's 0.003 is a third of the free-fall
# acceleration per frame here (187 / 148^2 = 0.0085 half-widths) and gave worse rollouts than
# 0.0003 at 32 tosses; 0.001 beat 0.0005 at 128 tosses (22% vs 28% position, 3% vs 6% penetration).
_TRAIN = ("train.threads=1", "train.batch_size=32", "train.lr_init=1e-3", "augment.noise_std=0.001",
          "valid.rollout_scenes=8", "valid.rollout_steps=50")
_COMPILED = ("train.compile=true",)   # as the real_cubes recipe: 1.29x the steps/s there, the same run
_ZOO_RUN = load_recipe("real_cubes").runs[0]
RECIPE, RECIPE_STEPS = tuple(_ZOO_RUN.overrides), _ZOO_RUN.steps
PRESETS = {
    "tiny": Preset(test=1, valid=0, sizes=(1, 2), seeds=(0,), model="tiny", steps=30,
                   train=_TRAIN + ("valid.every=0", "train.checkpoint_every=30"), baseline_budget=3,
                   baseline_tosses=None,
                   ablation_size=2, noise_size=2, vertex_noise=(0.05,), track_noise=(0.5,), plots=False),
    "quick": Preset(test=96, valid=32, sizes=(8, 32, 128), seeds=(0,), model="cpu", steps=6000,
                    train=_TRAIN + _COMPILED + ("train.lr_decay_steps=6000", "valid.every=1000",
                                                "train.checkpoint_every=1000"),
                    baseline_budget=120, ablation_size=128, noise_size=32, vertex_noise=(0.02, 0.1),
                    track_noise=(0.02, 0.1)),
    "full": Preset(test=96, valid=32, sizes=(8, 16, 32, 64, 128, 256), seeds=(0, 1, 2), model="cpu", steps=30000,
                   train=_TRAIN + _COMPILED + ("train.lr_decay_steps=10000", "valid.every=2000"),
                   baseline_budget=200, ablation_size=256, noise_size=256, vertex_noise=(0.01, 0.03, 0.1),
                   track_noise=(0.01, 0.03, 0.1)),
    # the ablations (Fig. 5) and the noise study (Fig. 7) on the zoo's real_cubes: its recipe's
    # settings and 256 tosses; the full model is the shipped file itself (its tosses and settings
    # checked), the other six trained: ~2 h with --workers 2 on 2 cores
    "zoo": Preset(test=96, valid=32, sizes=(256,), seeds=(0,), model="cpu", steps=RECIPE_STEPS, train=RECIPE,
                  baseline_budget=200, ablation_size=256, noise_size=256, vertex_noise=(0.01, 0.1),
                  track_noise=(0.1,), zoo="real_cubes"),
}


# ---- stages ----------------------------------------------------------------------------------

def split_stage(src: Path, out: Path, p: Preset, preset: str) -> tuple[dict[int, np.ndarray], dict]:
    """Every toss of src and their split, written to split.json; an impossible training size is
    refused before anything is trained. Returns (tosses, split)."""
    tosses = read_tosses(src)
    split = make_split(duplicate_groups(tosses), p.test, p.valid)
    for n in p.sizes:
        for s in p.seeds:
            training_ids(split, n, s)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "split.json", {**split, "src": str(src), "preset": preset,
                                    "note": "pool: groups of rotated copies, in the order training subsets take them"})
    return tosses, split


def external_stage(test_dir: Path | None, src: Path, out: Path, tosses: dict[int, np.ndarray]) -> dict | None:
    """--test-dir's tosses as a dataset, and which of them are copies of src's."""
    if test_dir is None:
        return None
    ext = read_tosses(Path(test_dir))
    external = {"dir": str(test_dir), "data": import_stage(Path(test_dir), out / "data" / "external",
                                                           {"test": sorted(ext)}),
                "overlap": overlaps(ext, tosses)}
    if external["overlap"]:
        say(f"warning: {len(external['overlap'])} --test-dir tosses are copies of tosses in {src}")
    return external


def training_sets(src: Path, out: Path, p: Preset, split: dict) -> dict[tuple[int, int], tuple[Path, list[int], list[str]]]:
    """{(size, seed): (dataset, training toss ids, training overrides)} of the main GNS runs."""
    sets = {}
    for n in p.sizes:
        for s in p.seeds:
            ids = training_ids(split, n, s)
            splits = {"train": ids, **({"valid": split["valid"]} if split["valid"] else {})}
            data = import_stage(src, out / "data" / f"train_n{n}_s{s}", splits)
            sets[(n, s)] = (data, ids, [f"train.steps={p.steps}", f"train.seed={s}", *p.train])
    return sets


def gns_runs(p: Preset, sets: dict) -> dict[str, tuple[Path, list[str]]]:
    """{run name: (dataset, training overrides)}: the main runs, the ablations, the noise levels."""
    runs = {f"gns_n{n}_s{s}": (data, over) for (n, s), (data, _, over) in sets.items()}
    data_a, _, over_a = sets[(p.ablation_size, p.seeds[0])]
    for name, (_, extra) in ABLATIONS.items():
        runs[f"ablation_{name}"] = (data_a, over_a + extra)
    data_n, _, over_n = sets[(p.noise_size, p.seeds[0])]
    for level in p.vertex_noise:
        runs[f"vertex_noise_{level:g}"] = (data_n, over_n + [f"augment.vertex_noise={level}"])
    for level in p.track_noise:
        runs[f"track_noise_{level:g}"] = (data_n, over_n + [f"augment.track_noise={level}"])
    return runs


def train_one(data: Path, run: Path, model: str, over: list[str]) -> tuple[Path, float | None, int]:
    """One GNS run trained (or skipped when done): its checkpoint, the seconds it trained (None
    when it had nothing left to train) and the step it started from. Top-level, so that
    --workers can run it in another process."""
    t0, before = time.perf_counter(), trained_step(run)
    ckpt = train_stage(data, run, model, over)
    return ckpt, (time.perf_counter() - t0 if trained_step(run) != before else None), before


def pooled_job(kind: str, *args):
    """A job of the pipeline's one pool: a GNS training (train_one) or, beside the first trainings,
    the engines' identification (baselines_job). Top-level: spawned workers run it."""
    return train_one(*args) if kind == "train" else baselines_job(*args)


def baselines_job(out: Path, sets: dict, test_data: Path, p: Preset, external_data: Path | None) -> dict:
    """pipelines.real_cubes_baselines.baselines_stage on the training sets: in a worker it writes
    the costs file itself, which the pipeline reads again once the pool is done."""
    return baselines_stage(out / "baseline", {k: (data, ids) for k, (data, ids, _) in sets.items()}, test_data,
                           available_engines(), p.baseline_budget, p.baseline_tosses, Costs(out / "costs.json"),
                           external_data=external_data, plots_for=(max(p.sizes), p.seeds[0]) if p.plots else None)


def fit_and_train(out: Path, p: Preset, sets: dict, runs: dict, test_data: Path, external: dict | None,
                  workers: int = 1) -> tuple[dict, dict]:
    """The engines identified and every GNS run trained (or skipped when done), `workers` jobs at a
    time: the fits (minutes on one core) run beside the first trainings, not before them.
    Returns (the baselines, {run name: (checkpoint, seconds trained or None, starting step)})."""
    largest = f"gns_n{max(p.sizes)}_s{p.seeds[0]}"
    shipped = {}
    if p.zoo is not None:
        ckpt = zoo_model_as_run(p.zoo, runs[largest][0], p.model, runs[largest][1])
        if ckpt is None:
            say(f"zoo: {p.zoo} was not trained on these tosses with these settings: {largest} is trained")
        else:
            say(f"zoo: {largest} is the shipped {p.zoo} ({ckpt}), scored as it is")
            shipped[largest] = ckpt
    jobs = {"baselines": ("baselines", out, sets, test_data, p, external["data"] if external is not None else None)}
    jobs.update({name: ("train", data, out / "runs" / name, p.model, over)
                 for name, (data, over) in runs.items() if name not in shipped})
    done_jobs = in_processes(pooled_job, jobs, workers)
    base = done_jobs.pop("baselines")
    done_jobs.update({name: (ckpt, None, -1) for name, ckpt in shipped.items()})
    return base, done_jobs


def gns_stage(out: Path, p: Preset, runs: dict, trained: dict, test_data: Path, external: dict | None,
              costs: Costs) -> tuple[dict, dict]:
    """Every GNS run (trained: fit_and_train's) scored on the test tosses (and on --test-dir's);
    the ablation size's model also without shape matching. Returns (evaluations, external
    evaluations)."""
    largest = f"gns_n{max(p.sizes)}_s{p.seeds[0]}"
    evals, ext_evals = {}, {}
    for name in runs:
        ckpt, seconds, before = trained[name]
        if seconds is not None:  # it trained: the checkpoint's total, else this call's time added to any earlier
            total = training_seconds(out / "runs" / name)
            earlier = costs.data.get(f"train {name}", 0.0) if before > 0 else 0.0
            costs.add(f"train {name}", total if total is not None else earlier + seconds)
        plots = out / "plots" / name if p.plots and name == largest else None
        evals[name] = gns_eval_stage(out / "eval" / f"{name}.json", ckpt, test_data, costs, plots_dir=plots)
        if name == f"gns_n{p.ablation_size}_s{p.seeds[0]}":
            evals["ablation_nosm"] = gns_eval_stage(out / "eval" / "ablation_nosm.json", ckpt, test_data, costs,
                                                    shape_matching=False)
        if external is not None and name.startswith("gns_"):
            ext_evals[name] = gns_eval_stage(out / "eval" / f"{name}.external.json", ckpt, external["data"], costs)
    return evals, ext_evals


def _scored_on(results: dict | None, data: Path) -> bool:
    """Whether saved results were computed on exactly the test tosses of `data`."""
    if results is None:
        return False
    scored = [r["scene_id"] for r in results.get("per_scene", [])] + list(results.get("diverged_scenes", []))
    return sorted(scored) == sorted(Dataset(data).meta["splits"]["test"]["toss_ids"])


def gns_eval_stage(path: Path, ckpt: Path, data: Path, costs: Costs, shape_matching: bool = True,
                   plots_dir: Path | None = None) -> dict:
    results = done(path, ckpt)
    if _scored_on(results, data):
        return results
    t0 = time.perf_counter()
    # at every recorded frame, the instants the engines are scored at; read between steps by the
    # spline for every model, the shipped file (which holds a learned reader) as the runs beside it
    results, *_ = evaluate_run(ckpt, data, "test", shape_matching=shape_matching, plots_dir=plots_dir, progress=False,
                               at_data_rate=True, between="spline")
    results["checkpoint_step"] = int(read_checkpoint(ckpt)["step"])
    write_json(path, results)
    costs.add(f"eval {path.stem}", time.perf_counter() - t0)
    return results


# ---- the experiment ----------------------------------------------------------------------------

def check_preset(p: Preset) -> None:
    if p.ablation_size not in p.sizes or p.noise_size not in p.sizes:
        raise ValueError("ablation_size and noise_size must be training sizes of the preset")


def run(preset: str, src: Path, out: Path, test_dir: Path | None = None, workers: int = 1) -> dict:
    p = PRESETS[preset]
    check_preset(p)
    src = Path(src)
    if not src.is_dir():
        raise DataError(f"source folder does not exist: {src}")
    if test_dir is not None and not Path(test_dir).is_dir():
        raise DataError(f"--test-dir folder does not exist: {test_dir}")
    check_writable(out)
    t_start = time.perf_counter()
    tosses, split = split_stage(src, out, p, preset)
    say(f"split: {len(split['test'])} test, {len(split['valid'])} valid, {sum(map(len, split['pool']))} pool tosses; "
        f"{len(split['duplicates'])} groups of copies kept together")
    test_data = import_stage(src, out / "data" / "test", {"test": split["test"]})
    external = external_stage(test_dir, src, out, tosses)
    sets = training_sets(src, out, p, split)
    runs = gns_runs(p, sets)
    base, trained = fit_and_train(out, p, sets, runs, test_data, external, workers)
    costs = Costs(out / "costs.json")   # read after the pool: the fits wrote theirs, in a worker or here
    evals, ext_evals = gns_stage(out, p, runs, trained, test_data, external, costs)
    results = collect(preset, p, src, split, evals, base, external, ext_evals, costs)
    results["pipeline_seconds_this_call"] = round(time.perf_counter() - t_start, 1)
    write_json(out / "results.json", results)
    make_plots(out / "plots", results)
    path = report(out, results)
    say(f"report: {path}")
    return results


def _paired(gns: dict, base: dict, key: str = "position_error_pct") -> float:
    """Fraction of test tosses on which the GNS has the lower error."""
    b = {r["scene_id"]: r[key] for r in base["per_scene"]}
    wins = [r[key] < b[r["scene_id"]] for r in gns["per_scene"] if r["scene_id"] in b]
    return float(np.mean(wins)) if wins else float("nan")


def collect(preset, p, src, split, evals, base, external, ext_evals, costs) -> dict:
    engines = list(base["fits"])
    sizes = {}
    for n in p.sizes:
        rows = []
        for s in p.seeds:
            g, name = evals[f"gns_n{n}_s{s}"], f"n{n}_s{s}"
            rows.append({"seed": s, "gns": summary(g), **{e: summary(base["evals"][e][name]) for e in engines},
                         "fits": {e: fit_summary(base["fits"][e][name]) for e in engines},
                         "gns_wins": {e: {"position": _paired(g, base["evals"][e][name]),
                                          "rotation": _paired(g, base["evals"][e][name], "rotation_error_deg")}
                                      for e in engines}})
        sizes[str(n)] = rows
    full_name = f"gns_n{p.ablation_size}_s{p.seeds[0]}"
    full_label = f"full model (the zoo's {p.zoo})" if evals[full_name].get("run", "").endswith(f"{p.zoo}.pt") else "full model"
    ablations = {full_label: summary(evals[full_name]), "no shape matching": summary(evals["ablation_nosm"])}
    ablations.update({label: summary(evals[f"ablation_{k}"]) for k, (label, _) in ABLATIONS.items()})
    noise_ref = summary(evals[f"gns_n{p.noise_size}_s{p.seeds[0]}"])
    noise = {"vertex": {"0": noise_ref, **{f"{v:g}": summary(evals[f"vertex_noise_{v:g}"]) for v in p.vertex_noise}},
             "track": {"0": noise_ref, **{f"{v:g}": summary(evals[f"track_noise_{v:g}"]) for v in p.track_noise}}}
    ext = None
    if external is not None:
        ext = {"dir": external["dir"], "overlap": {str(k): v for k, v in external["overlap"].items()},
               "pybullet_published": summary(base["external"]["published"][""]),
               "sizes": {str(n): [{"seed": s, "gns": summary(ext_evals[f"gns_n{n}_s{s}"]),
                                   **{e: summary(base["external"][e][f"n{n}_s{s}"]) for e in engines}}
                                  for s in p.seeds] for n in p.sizes}}
    return {"preset": preset, "src": str(src), "preset_settings": asdict(p),
            "split": {k: split[k] for k in ("seed", "num_tosses", "duplicates")} | {
                "test": len(split["test"]), "valid": len(split["valid"]), "pool": sum(map(len, split["pool"]))},
            "engines": engines, "sizes": sizes, "pybullet_published": summary(base["evals"]["published"][""]),
            "true_penetration_pct": base["evals"]["published"][""]["true_penetration_pct"],
            "ablation_size": p.ablation_size, "ablations": ablations, "noise_size": p.noise_size, "noise": noise,
            "external": ext, "costs_seconds": costs.data,
            "total_cost_seconds": round(sum(costs.data.values()), 1)}


def main(argv=None) -> int:
    ap = real_cubes_parser("real_cubes", __doc__, PRESETS, "quick")
    ap.add_argument("--test-dir", type=Path, help="a further folder of N.pt tosses to score everything on")
    ap.add_argument("--fresh", action="store_true", help="delete the output folder first instead of resuming")
    ap.add_argument("--workers", type=int, default=1,
                    help="train this many GNS runs at once, each in its own process (one core each)")
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error(f"--workers must be at least 1, not {a.workers}")
    out = a.out or Path("runs") / f"real_cubes_{a.preset}"
    import torch
    torch.set_num_threads(1)  # rollouts of 8-vertex graphs: a second thread only waits on the first

    def stages():
        if a.fresh:
            remove_output(out, OUTPUTS)
        run(a.preset, a.src, out, a.test_dir, a.workers)
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
