"""The paper's Fig. 6: the GNS and a GRU on MuJoCo cube tosses with hard, medium and soft contact.

    python -m pipelines.stiffness --preset quick|full [--out runs/stiffness_<preset>] [--starts-from DATA] [--workers N]

Data: `datagen toss --engine mujoco --stiffness LEVEL` (configs/mujoco_cubes.toml): one cube of the
real ContactNets set-up tossed onto a table from starts drawn from a distribution fitted to the
456 shared ContactNets tosses, simulated by MuJoCo with solref time constants 0.02 s (hard),
0.0577 s (medium) and 0.1 s (soft), Parmar et al.'s stiffnesses 2500, 300 and 100. Every level
uses the same seed, so the three levels toss the same starts; the training sets of one level are
nested (the first n tosses of the largest), the test tosses held out (another split's draws).
--starts-from DATA refits the start distribution to the ContactNets tosses in DATA (its
tosses_processed/N.pt) instead of the shipped fit.

Models, per level and training size: the GNS with the real-cube zoo model's settings
(configs/recipes/real_cubes.toml: gns_cpu with L=10, a time step of 8 frames), and the GRU of
baselines/gru.py on the same tosses with the same optimiser steps and batch size (so the same
number of training windows; their wall times are reported). Both are scored on the level's test
tosses from their first 3 states (frames 0, 8, 16) at every recorded frame with the ContactNets
metrics: the GNS by `gns eval --at-data-rate --symmetrize d2` (as the zoo card scores it), the GRU
by baselines.gru (the same formulas). The penetration each level's own data show is measured on
its test tosses.

The command lines run in-process (datagen.cli.main, gns.cli.main). Output in --out: report.md,
results.json, plots/error_vs_size.png, costs.json and costs/ (one file per model, level and
size), and the data/, runs/, eval/ folders of the stages. Rerunning skips finished stages and
resumes an interrupted GNS or GRU training where it stopped. --workers N trains N models at a
time (every GNS, then every GRU: the longer first), one process and core each. Presets:
  tiny   the test suite's smoke run: 2 levels, sizes 2 and 4, a tiny GNS and GRU, 4 steps
  quick  sizes 30, 100, 300; 3000 steps each; 100 test tosses a level (~1 h on one core)
  full   sizes 100, 1000, 10000 (Allen et al.'s); the recipe's 40,000 steps; 200 test tosses
         (~4 h on 2 cores with --workers 2)
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from baselines import gru
from datagen.shards import Dataset
from plumbing import DataError, check_writable
from pipelines.common import Costs, guarded, in_processes, remove_output, say, trained_step, training_seconds
from pipelines.stiffness_report import finding, plot, report

LEVELS = ("soft", "medium", "hard")     # soft to hard: the order of every table and plot
OUTPUTS = {"costs.json", "costs", "data", "runs", "eval", "plots", "results.json", "report.md", "starts.toml"}
EVAL_FLAGS = ("--at-data-rate", "--symmetrize", "d2")


@dataclass(frozen=True)
class Preset:
    levels: tuple[str, ...]
    sizes: tuple[int, ...]           # training tosses per level
    test: int                        # held-out test tosses per level
    valid: int                       # validation tosses (the GNS trainer's curves)
    model: str                       # gns preset
    steps: int                       # optimiser steps of every GNS and GRU run
    lr_decay_steps: int
    train: tuple[str, ...] = ()      # GNS overrides on top of the real_cubes recipe's
    gru: dict = field(default_factory=dict)   # GRUConfig fields
    seed: int = 0


PRESETS = {
    "tiny": Preset(levels=("soft", "hard"), sizes=(2, 4), test=2, valid=0, model="gns_tiny", steps=4, lr_decay_steps=4,
                   train=("model.message_passing_steps=1", "train.batch_size=2", "valid.every=0", "train.compile=false",
                          "train.checkpoint_every=4", "features.normalizer_steps=4", "train.log_every=2"),
                   gru={"hidden": 8, "layers": 1, "log_every": 2}),
    "quick": Preset(levels=LEVELS, sizes=(30, 100, 300), test=100, valid=16, model="gns_cpu", steps=3000,
                    lr_decay_steps=3000, train=("valid.every=1000", "train.checkpoint_every=1000")),
    # checkpointed often: the preset outlasts a working day and resumes
    "full": Preset(levels=LEVELS, sizes=(100, 1000, 10000), test=200, valid=32, model="gns_cpu", steps=40000,
                   lr_decay_steps=13333, train=("train.checkpoint_every=1000",)),
}


def gns_overrides(p: Preset) -> list[str]:
    """The real-cube zoo model's settings (its recipe), the preset's steps and schedule on top."""
    from pipelines.recipe import load_recipe
    recipe = load_recipe("real_cubes").runs[0]
    overrides = [*recipe.overrides, f"train.steps={p.steps}", f"train.seed={p.seed}",
                 f"train.lr_decay_steps={p.lr_decay_steps}", *p.train]
    # one entry a key, the last given (the preset's over the recipe's), so the report lists each once
    return list({o.split("=", 1)[0]: o for o in overrides}.values())


def gru_config(p: Preset) -> gru.GRUConfig:
    """The GRU's budget: the GNS's optimiser steps, batch size (tosses a step, as the GNS's windows)
    and learning-rate schedule."""
    batch = [int(o.split("=", 1)[1]) for o in gns_overrides(p) if o.startswith("train.batch_size=")][-1]
    return gru.GRUConfig(steps=p.steps, batch_size=batch, lr_decay_steps=p.lr_decay_steps, seed=p.seed, **p.gru)


# ---- running the command lines in-process ------------------------------------------------------

def command(main, argv: list[str], what: str) -> None:
    """A command line's main() in this process; a failure (its one error line already printed)
    becomes a DataError naming the command."""
    argv = [str(a) for a in argv]
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    if code not in (None, 0):
        raise DataError(f"{what} failed (exit status {code}): {' '.join(argv)}")


def datagen(argv: list[str]) -> None:
    from datagen.cli import main
    command(main, argv, "datagen")


def gns(argv: list[str]) -> None:
    from gns.cli import main
    command(main, argv, "gns")


# ---- stages ------------------------------------------------------------------------------------

def data_stage(out: Path, level: str, counts: dict[str, int], seed: int, config: Path | None, workers: int = 1
               ) -> bool:
    """A level's tosses (counts per split) in `out`, made (on `workers` processes) unless it
    already holds exactly them. Returns whether it made them."""
    from datagen.mujoco_tosses import load_config
    want = load_config(config, stiffness=level)
    try:
        ds = Dataset(out)
        if ds.meta.get("config") == want and ds.meta.get("seed") == seed and \
                all(ds.num_scenes(s) == n for s, n in counts.items()):
            return False
    except DataError:
        pass
    say(f"data: {sum(counts.values())} {level} tosses into {out}")
    datagen(["toss", "--engine", "mujoco", "--stiffness", level, "--scenes", counts.get("train", 0),
             "--valid", counts.get("valid", 0), "--test", counts.get("test", 0), "--seed", seed, "--out", out,
             "--workers", workers, "--quiet", "--overwrite", *(["--config", config] if config else [])])
    return True


def _settings_guard(run: Path, settings: dict) -> None:
    """A run folder records what it was trained with; settings that change what it learns are
    refused, not mixed (pipelines.common.SETTINGS_FREE, such as compiling, may change)."""
    path = run / "pipeline_settings.json"
    if path.exists():
        old = json.loads(path.read_text())
        from gns.config import config_differences, config_to_dict
        from pipelines.common import SETTINGS_FREE
        if old.get("data") != settings["data"] or config_differences(config_to_dict(_config(old)), _config(settings),
                                                                      ignore=SETTINGS_FREE):
            raise DataError(f"{run} was trained with other settings: delete it (or the output with --fresh) to train "
                            f"again")
    run.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=1) + "\n")


def _config(settings: dict):
    """The Config a run's recorded settings resolve to."""
    from gns.config import build_config
    from plumbing import config_path
    return build_config(path=config_path(settings["config"]), overrides=list(settings["set"]))


def gns_train_stage(run: Path, data: Path, p: Preset, costs: Costs) -> None:
    overrides = gns_overrides(p)
    _settings_guard(run, {"data": str(data), "config": p.model, "set": overrides})
    step = trained_step(run)
    if step >= p.steps:
        return
    say(f"gns train: {run} ({p.steps} steps{f', resuming at {step}' if step > 0 else ''})")
    t0 = time.perf_counter()
    gns(["train", "--data", data, "--out", run, "--config", p.model,
         *(["--resume"] if step >= 0 else ["--overwrite"]), "--set", *overrides])
    seconds = training_seconds(run)
    costs.add(f"train gns {run.name}", seconds if seconds is not None else time.perf_counter() - t0)


def _current(path: Path, step: int, test: Path) -> dict | None:
    """Saved scores if made from this checkpoint step on this very test set."""
    if not path.exists():
        return None
    try:
        r = json.loads(path.read_text())
    except ValueError:
        return None
    return r if r.get("checkpoint_step") == step and r.get("test_fingerprint") == Dataset(test).fingerprint else None


def _write_json(path: Path, obj) -> None:
    from plumbing import atomic_file
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")


def gns_eval_stage(path: Path, run: Path, test: Path, costs: Costs) -> dict:
    step = trained_step(run)
    saved = _current(path, step, test)
    if saved is not None:
        return saved
    t0 = time.perf_counter()
    raw = path.with_suffix(".gns.json")
    gns(["eval", "--run", run, "--data", test, *EVAL_FLAGS, "--json", raw])
    r = json.loads(raw.read_text())
    r.update(checkpoint_step=step, test_fingerprint=Dataset(test).fingerprint)
    _write_json(path, r)
    raw.unlink()
    costs.add(f"eval {path.stem}", time.perf_counter() - t0)
    return r


def gru_stage(run: Path, data: Path, test: Path, path: Path, p: Preset, costs: Costs) -> dict:
    cfg = gru_config(p)
    if not gru.trained(run, cfg):
        say(f"gru train: {run} ({cfg.steps} steps)")
        gru.train(data, run, cfg, log=say)
        costs.add(f"train gru {run.name}", gru.load(run)[1]["train_seconds"])   # resumed segments summed
    saved = _current(path, cfg.steps, test)
    if saved is not None and saved.get("train_seconds") == gru.load(run)[1]["train_seconds"]:
        return saved
    r = gru.evaluate(run, test)
    r["test_fingerprint"] = Dataset(test).fingerprint
    _write_json(path, r)
    return r


def penetration_stage(test: Path) -> dict:
    from datagen.mujoco_tosses import dataset_penetration
    ds = Dataset(test)
    return {**dataset_penetration(ds.load("test")), "timeconst": ds.meta["config"]["contact"]["timeconst"],
            "dampratio": ds.meta["config"]["contact"]["dampratio"]}


def starts_stage(src: Path | None, out: Path) -> Path | None:
    """--starts-from: the start distribution refitted to the ContactNets tosses of src, as a
    config file (OUT/starts.toml) that datagen toss reads; None: the shipped fit."""
    if src is None:
        return None
    from datagen.contactnets import list_toss_ids, read_experiment, read_toss, toss_to_scene
    from datagen.mujoco_tosses import fit_starts
    root = src / "tosses_processed" if (src / "tosses_processed").is_dir() else src
    ids = list_toss_ids(src)
    if not ids:
        raise DataError(f"--starts-from {src}: no N.pt toss files")
    consts = read_experiment(src)
    fit = fit_starts([toss_to_scene(read_toss(root / f"{i}.pt"), i, f"{i}.pt", consts) for i in ids],
                     1.0 / float(consts["dt"]), float(consts["g"]))
    n = fit.pop("num_tosses")
    lines = [f"# the start distribution fitted to the {n} ContactNets tosses in {src}", "[start]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in fit.items()]
    path = out / "starts.toml"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


# ---- the experiment ----------------------------------------------------------------------------

SUMMARY = ("position_error_pct", "rotation_error_deg", "penetration_pct", "true_penetration_pct")


def _summary(r: dict) -> dict:
    return {k: r.get(k) for k in SUMMARY}


def size_stage(preset: str, out: Path, level: str, n: int, model: str) -> tuple[dict, float | None, dict]:
    """The GNS or the GRU (`model`) of one level and training size, trained and scored on the
    level's test tosses; returns its scores, its training seconds and the stage costs. Top-level, so that --workers can
    run it in a process of its own: its costs go to a file of its own (costs/MODEL_LEVEL_nN.json)."""
    import torch
    # one thread, as main() sets in this pipeline's own process: a spawned worker starts at
    # torch's default (every core), and two workers' GRUs ran 4 threads on 2 cores, ~12 steps/s
    # each instead of ~27
    torch.set_num_threads(1)
    p = PRESETS[preset]
    name, data, test = f"{level}_n{n}", out / "data" / level / f"train_n{n}", out / "data" / level / "test"
    costs = Costs(out / "costs" / f"{model}_{name}.json")
    run, path = out / "runs" / f"{model}_{name}", out / "eval" / f"{model}_{name}.json"
    if model == "gns":
        gns_train_stage(run, data, p, costs)
        r = gns_eval_stage(path, run, test, costs)
        seconds = costs.data.get(f"train gns {run.name}")
    else:
        r = gru_stage(run, data, test, path, p, costs)
        seconds = r.get("train_seconds")
    say(f"{name}: {model.upper()} {r['position_error_pct']:.1f}% / {r['rotation_error_deg']:.1f} deg")
    return _summary(r), seconds, costs.data


def run(preset: str, out: Path, starts_from: Path | None = None, workers: int = 1) -> dict:
    p = PRESETS[preset]
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    costs = Costs(out / "costs.json")
    config = starts_stage(Path(starts_from) if starts_from else None, out)
    results = {"preset": preset, "settings": asdict(p), "gns_overrides": gns_overrides(p),
               "gru_config": asdict(gru_config(p)), "eval_flags": list(EVAL_FLAGS),
               "starts": str(starts_from) if starts_from else "configs/mujoco_cubes.toml (fitted to the 456 shared "
                                                            "ContactNets tosses)",
               "levels": {}}
    for level in p.levels:
        t0 = time.perf_counter()
        made = data_stage(out / "data" / level / "test", level, {"test": p.test}, p.seed, config, workers)
        for n in p.sizes:
            made |= data_stage(out / "data" / level / f"train_n{n}", level, {"train": n, "valid": p.valid}, p.seed,
                               config, workers)
        if made:
            costs.add(f"data {level}", time.perf_counter() - t0)
    # every GNS before any GRU (the longer jobs first keep both workers busy to the end), and the
    # extreme levels before the middle ones: soft against hard, the finding, is complete first
    extremes_first = sorted(p.levels, key=lambda level: level not in (p.levels[0], p.levels[-1]))
    units = in_processes(size_stage, {(model, level, n): (preset, out, level, n, model) for model in ("gns", "gru")
                                      for level in extremes_first for n in p.sizes}, workers)
    unit_costs = {}
    for level in p.levels:
        sizes = {}
        for n in p.sizes:
            (g, g_seconds, g_costs), (r, r_seconds, r_costs) = units[("gns", level, n)], units[("gru", level, n)]
            sizes[str(n)] = {"gns": g, "gru": r, "gns_train_seconds": g_seconds, "gru_train_seconds": r_seconds}
            unit_costs.update(g_costs)
            unit_costs.update(r_costs)
        results["levels"][level] = {"penetration": penetration_stage(out / "data" / level / "test"), "sizes": sizes}
    results["finding"] = finding(results)
    results["costs_seconds"] = {**costs.data, **unit_costs}
    results["pipeline_seconds_this_call"] = round(time.perf_counter() - t_start, 1)
    _write_json(out / "results.json", results)
    plot(out / "plots" / "error_vs_size.png", results)
    path = report(out, results)
    say(f"report: {path}")
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.stiffness", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="quick")
    ap.add_argument("--out", type=Path, help="output folder (default runs/stiffness_<preset>)")
    ap.add_argument("--starts-from", type=Path, metavar="DATA",
                    help="refit the start distribution to the ContactNets tosses in DATA (tosses_processed/N.pt)")
    ap.add_argument("--fresh", action="store_true", help="delete the output folder first instead of resuming")
    ap.add_argument("--workers", type=int, default=1,
                    help="train this many models (GNS or GRU) at once, each in its own process (one core each)")
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error(f"--workers must be at least 1, not {a.workers}")
    out = a.out or Path("runs") / f"stiffness_{a.preset}"
    import torch
    torch.set_num_threads(1)

    def stages():
        if a.fresh:
            remove_output(out, OUTPUTS)
        run(a.preset, out, a.starts_from, a.workers)
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
