"""The analytic baselines of the real-cube experiments: PyBullet and MuJoCo, each identified on
the GNS's training tosses and rolled out on the same test tosses (docs/results.md).

    python -m pipelines.real_cubes_baselines --src DATA [--sizes 16 64 256] [--engines pybullet mujoco]
        [--budget 120] [--fit-tosses 64] [--out runs/real_cubes_baselines]

pipelines/real_cubes.py runs these stages beside its GNS trainings; run alone, this measures the
baselines on the same split without training anything (report: baselines.md, results.json).
Each fit and evaluation is saved under baseline/ and skipped on a rerun if it was made from the
same tosses and settings. MuJoCo is an optional extra: without it, its rows are left out with
one warning line (or, asked for by name here, one error line).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from baselines import baseline_engine
from baselines.pybullet import PUBLISHED
from datagen.shards import Dataset
from plumbing import DataError
from baselines.toss import evaluate_baseline
from gns.evaluate import write_json
from gns.metrics import METRICS
from pipelines.common import Costs, guarded, say
from pipelines.real_cubes_data import (duplicate_groups, import_stage, make_split, read_tosses, real_cubes_parser,
                                      training_ids)
from pipelines.real_cubes_report import ENGINE_LABELS, fit_summary, fits_table, number, summary

ENGINES = ("pybullet", "mujoco")


def available_engines(wanted=ENGINES, strict: bool = False) -> list[str]:
    """The wanted engines that can run here; MuJoCo only if installed. strict: a missing one is
    an error (one line), otherwise a warning line and it is left out."""
    from baselines.mujoco import MISSING, available
    out = []
    for e in wanted:
        if e == "mujoco" and not available():
            if strict:
                raise DataError(MISSING)
            say(f"warning: {MISSING}; leaving it out")
            continue
        out.append(e)
    return out


def _search_settings(engine: str) -> dict:
    """What a fit was searched over: a change of bounds or fitted names makes saved fits stale."""
    import importlib
    mod = importlib.import_module(f"baselines.{engine}")
    return {"bounds": [list(b) for b in mod.BOUNDS], "fitted": list(mod.FIT)}


def fit_stage(path: Path, data: Path, ids: list[int], engine: str, budget: int, seed: int,
              fit_tosses: int | None, costs) -> dict:
    """Identify `engine` on the train split of `data` (the tosses `ids`), unless saved."""
    key = {"engine": engine, "train_ids": ids, "budget": budget, "seed": seed, "max_tosses": fit_tosses,
           "search": _search_settings(engine)}
    if path.exists():
        saved = json.loads(path.read_text())
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    subset = f", a random {fit_tosses} of them" if fit_tosses and len(ids) > fit_tosses else ""
    say(f"baseline: fitting {ENGINE_LABELS[engine]} on {len(ids)} tosses{subset} ({budget} evaluations)")
    _, _, fit_parameters = baseline_engine(engine)
    fit = fit_parameters(Dataset(data).load("train"), budget=budget, seed=seed, max_tosses=fit_tosses)
    out = {**key, **{k: v for k, v in fit.items() if k != "params"}, "params": asdict(fit["params"])}
    write_json(path, out)
    costs.add(f"baseline fit {path.stem}", fit["seconds"])
    return out


def _scored_on(results: dict | None, data: Path) -> bool:
    return results is not None and [r["scene_id"] for r in results.get("per_scene", [])] == \
        Dataset(data).meta["splits"]["test"]["toss_ids"]


def eval_stage(path: Path, data: Path, engine: str, params: dict, costs, plots_dir: Path | None = None) -> dict:
    """Roll `engine` with `params` out on the test split of `data` and score it, unless saved."""
    if path.exists():
        saved = json.loads(path.read_text())
        if saved.get("params") == params and saved.get("baseline", "pybullet") == engine and _scored_on(saved, data):
            return saved
    t0 = time.perf_counter()
    params_class, _, _ = baseline_engine(engine)
    results, *_ = evaluate_baseline(data, "test", params_class(**params), plots_dir=plots_dir, engine=engine)
    write_json(path, results)
    costs.add(f"eval {path.stem}", time.perf_counter() - t0)
    return results


def baselines_stage(out: Path, runs: dict, test_data: Path, engines: list[str], budget: int, fit_tosses: int | None,
                    costs, external_data: Path | None = None, plots_for: tuple | None = None) -> dict:
    """Every engine identified on every training set and scored on the test tosses.

    runs: {(n, seed): (dataset folder, training ids)}. Returns {"fits": {engine: {name: fit}},
    "evals": {engine or "published": {name: results}}, "external": the same on external_data},
    name = "n{n}_s{seed}"; "published" holds PyBullet with the published constants."""
    fits = {e: {} for e in engines}
    evals, ext = {e: {} for e in engines}, {e: {} for e in engines}
    evals["published"] = {"": eval_stage(out / "eval_published.json", test_data, "pybullet", PUBLISHED.to_dict(), costs)}
    if external_data is not None:
        ext["published"] = {"": eval_stage(out / "eval_published.external.json", external_data, "pybullet",
                                           PUBLISHED.to_dict(), costs)}
    for engine in engines:
        tag = "" if engine == "pybullet" else f"{engine}_"  # PyBullet keeps its earlier file names
        for (n, s), (data, ids) in runs.items():
            name = f"n{n}_s{s}"
            fits[engine][name] = fit = fit_stage(out / f"fit_{tag}{name}.json", data, ids, engine, budget, s,
                                                 fit_tosses, costs)
            plots = out.parent / "plots" / f"{engine}_{name}" if plots_for == (n, s) else None
            evals[engine][name] = eval_stage(out / f"eval_{tag}{name}.json", test_data, engine, fit["params"], costs,
                                             plots_dir=plots)
            if external_data is not None:
                ext[engine][name] = eval_stage(out / f"eval_{tag}{name}.external.json", external_data, engine,
                                               fit["params"], costs)
    return {"fits": fits, "evals": evals, "external": ext if external_data is not None else None}


# ---- alone: the baselines on the pipeline's split, no GNS -----------------------------------------

def run(src: Path, out: Path, sizes: list[int], engines: list[str], budget: int, fit_tosses: int | None,
        seed: int = 0, test: int | None = None, valid: int | None = None) -> dict:
    from pipelines.real_cubes import PRESETS  # which imports this module
    src = Path(src)
    if not src.is_dir():
        raise DataError(f"source folder does not exist: {src}")
    engines = available_engines(engines, strict=True)
    tosses = read_tosses(src)
    test = PRESETS["full"].test if test is None else test  # by default the presets' split
    valid = PRESETS["full"].valid if valid is None else valid
    split = make_split(duplicate_groups(tosses), test, valid)
    runs = {(n, seed): training_ids(split, n, seed) for n in sizes}
    out.mkdir(parents=True, exist_ok=True)
    costs = Costs(out / "costs.json")
    test_data = import_stage(src, out / "data" / "test", {"test": split["test"]})
    runs = {k: (import_stage(src, out / "data" / f"train_n{k[0]}_s{k[1]}", {"train": ids}), ids)
            for k, ids in runs.items()}
    res = baselines_stage(out / "baseline", runs, test_data, engines, budget, fit_tosses, costs)
    results = {"src": str(src), "test": len(split["test"]), "budget": budget, "fit_tosses": fit_tosses, "seed": seed,
               "published": summary(res["evals"]["published"][""]),
               "sizes": {str(n): {e: {**summary(res["evals"][e][f"n{n}_s{seed}"]),
                                      "fit": fit_summary(res["fits"][e][f"n{n}_s{seed}"])} for e in engines}
                         for n in sizes},
               "costs_seconds": costs.data}
    write_json(out / "results.json", results)
    cmd = " ".join(["python -m pipelines.real_cubes_baselines", "--src", str(src), "--out", str(out), "--sizes",
                    *map(str, sizes), "--engines", *engines, "--budget", str(budget), "--fit-tosses", str(fit_tosses or 0)]
                   + ([f"--test {test} --valid {valid}"] if (test, valid) != (PRESETS["full"].test, PRESETS["full"].valid)
                      else []))
    lines = [f"# Baselines on the real cube tosses ({results['test']} test tosses)", "", f"Made by `{cmd}`.", "",
             "| engine | training tosses | position % | rotation deg | penetration % | fit s | evaluation s |",
             "|---|---|---|---|---|---|---|"]
    pub = results["published"]
    lines.append("| PyBullet, published constants | - | " + " | ".join(number(pub[k]) for k in METRICS) + " | - | - |")
    for n in sizes:
        for e in engines:
            r = results["sizes"][str(n)][e]
            ev = costs.data.get(f"eval eval_{'' if e == 'pybullet' else e + '_'}n{n}_s{seed}")
            lines.append(f"| {ENGINE_LABELS[e]} | {n} | " + " | ".join(number(r[k]) for k in METRICS)
                         + f" | {r['fit']['seconds']:.0f} | {number(ev)} |")
    lines += ["", *fits_table([(e, n, seed, results["sizes"][str(n)][e]["fit"]) for n in sizes for e in engines]), ""]
    (out / "baselines.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return results


def main(argv=None) -> int:
    ap = real_cubes_parser("real_cubes_baselines", __doc__)
    ap.add_argument("--out", type=Path, default=Path("runs/real_cubes_baselines"))
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 64, 256], help="training set sizes")
    ap.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    ap.add_argument("--budget", type=int, default=120, help="objective evaluations per fit")
    ap.add_argument("--fit-tosses", type=int, default=64,
                    help="fit on a seeded random subset of at most this many training tosses (0: all)")
    ap.add_argument("--seed", type=int, default=0, help="training subset order and search seed")
    ap.add_argument("--test", type=int, help="test tosses (default: the presets' 96)")
    ap.add_argument("--valid", type=int, help="validation tosses kept out of training (default: the presets' 32)")
    a = ap.parse_args(argv)
    return guarded(lambda: run(a.src, a.out, a.sizes, a.engines, a.budget, a.fit_tosses or None, a.seed,
                               a.test, a.valid))


if __name__ == "__main__":
    sys.exit(main())
