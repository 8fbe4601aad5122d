"""Train a model by a named recipe (configs/recipes/NAME.toml), as the zoo's models were trained.

    python -m pipelines.recipe movi_a --out runs/zoo/movi_a [--data DIR] [--workers 2]
    python -m pipelines.recipe --list

A recipe is data: the training data it needs, the model preset, settings shared by every stage,
then stages. Each stage starts from the last one's weights (train.init_from) and inherits its
settings, changing only those it names; a stage with `cycles = n` is one schedule of n warm
restarts (each cycle from the last one's weights, the learning rate restarted, the next seed).
A stage with `contact = true` trains a contact network (LearnedSimulator.set_contact_model) from
the last run's weights: the model is then the last other run, with the last contact run rolling
out its objects in contact.
Every stage and cycle is a run folder of its own (OUT/runs/NAME[_k]); a rerun skips what is done
and resumes what was interrupted. At the end the model is exported to OUT/model.pt and scored on
the data's test split with each zoo card's rollout options (OUT/report.md, OUT/results.json); with
`between = true` the export holds the reader of the frames between a strided model's steps,
fitted on the training data (gns.between).
"""
from __future__ import annotations

import argparse
import json
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

from plumbing import config_dir
from plumbing import DataError

RECIPES = config_dir() / "recipes"
METRICS = ("position_error_pct", "rotation_error_deg", "penetration_pct")


@dataclass(frozen=True)
class Run:
    """One training run of a recipe: a stage, or one cycle of it."""
    name: str
    steps: int
    seed: int
    overrides: tuple[str, ...]   # gns train --set, on top of the model preset
    contact: bool = False        # trains the contact network


@dataclass(frozen=True)
class Recipe:
    name: str
    zoo: tuple[str, ...]
    model: str                   # a gns preset: gns_tiny, gns_cpu, gns_paper
    cost: str
    data: dict
    runs: tuple[Run, ...]
    between: bool = False        # export with the reader between steps fitted on the training data


def _value(v) -> str:
    """A TOML value as `--set` reads it."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return json.dumps(v)  # strings and lists: TOML's basic strings are JSON's


def _merge(into: dict, settings: dict, where: str) -> None:
    for section, table in settings.items():
        if not isinstance(table, dict):
            raise DataError(f"{where}: settings.{section} must be a table of keys")
        into.update({f"{section}.{k}": v for k, v in table.items()})


def recipe_names() -> list[str]:
    return sorted(p.stem for p in RECIPES.glob("*.toml"))


def load_recipe(name: str) -> Recipe:
    path = Path(name) if name.endswith(".toml") else RECIPES / f"{name}.toml"
    if not path.is_file():
        raise DataError(f"no recipe {name!r}; there are: {', '.join(recipe_names())}")
    try:
        with open(path, "rb") as f:
            raw = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise DataError(f"{path}: not valid TOML ({e})") from None
    where = path.name
    settings: dict = {}
    _merge(settings, raw.get("settings", {}), where)
    runs = []
    for i, stage in enumerate(raw.get("stage", [])):
        missing = {"name", "steps", "seed"} - set(stage)
        if missing:
            raise DataError(f"{where}: stage {i + 1} has no {', '.join(sorted(missing))}")
        _merge(settings, stage.get("settings", {}), f"{where} stage {stage['name']}")
        cycles = int(stage.get("cycles", 1))
        if cycles < 1:
            raise DataError(f"{where} stage {stage['name']}: cycles must be >= 1")
        sets = tuple(f"{k}={_value(v)}" for k, v in settings.items())
        for k in range(cycles):
            runs.append(Run(stage["name"] if cycles == 1 else f"{stage['name']}_{k + 1}", int(stage["steps"]),
                            int(stage["seed"]) + k, sets, bool(stage.get("contact", False))))
    if not runs:
        raise DataError(f"{where}: no [[stage]]")
    if all(r.contact for r in runs):
        raise DataError(f"{where}: every stage trains a contact network; the model itself needs one")
    return Recipe(path.stem, tuple(raw.get("zoo", ())), raw.get("model", "gns_cpu"), raw.get("cost", ""),
                  raw.get("data", {}), tuple(runs), bool(raw.get("between", False)))


def run_overrides(run: Run, previous: Path | None) -> list[str]:
    out = [*run.overrides, f"train.steps={run.steps}", f"train.seed={run.seed}"]
    if previous is not None:
        out.append(f"train.init_from={previous}")
    return out


def scene_sets(data: dict) -> list[str]:
    return [f"scene.{k}={_value(v)}" for k, v in data.get("scene", {}).items()]


def _check_fingerprint(recipe: Recipe, ds) -> None:
    from pipelines.common import say
    want = recipe.data.get("fingerprint")
    if want and ds.fingerprint != want:
        say(f"data: {ds.root} is not the recipe's dataset (fingerprint {str(ds.fingerprint)[:16]}, the recipe's "
            f"{want[:16]}): training goes on, on this data")


def data_stage_of(recipe: Recipe, out: Path, data: Path | None, src: Path | None, workers: int):
    """(training dataset, the folder of the test split it is scored on)."""
    from datagen.shards import Dataset
    from pipelines.common import data_stage
    d = recipe.data
    kind = d.get("kind", "datagen")
    if data is not None:
        ds = Dataset(data)
        _check_fingerprint(recipe, ds)
        return ds, data
    if kind == "datagen":
        counts = {s: int(d[s]) for s in ("train", "valid", "test") if int(d.get(s, 0)) > 0}
        ds = data_stage(out / "data", scene_sets(d), counts, int(d.get("seed", 0)), workers)
        return ds, ds.root
    if kind == "tilted_drops":
        from pipelines.diagnostic_45 import training_data_stage
        ds = training_data_stage(out / "data", {"train": int(d["train"]), "valid": int(d["valid"])}, int(d["seed"]),
                                 shapes=d.get("shapes", ("cube",)), max_heights=d.get("max_heights", (0.05,)))
        return ds, None
    if kind in ("contactnets", "contactnets_mujoco"):
        if src is None:
            raise DataError(f"recipe {recipe.name} trains on the real ContactNets cube tosses: give --src, the folder "
                            "holding tosses_processed/ (DAIRLab/contact-nets, data/)")
        from pipelines.real_cubes_data import duplicate_groups, import_stage, make_split, read_tosses, training_ids
        if not Path(src).is_dir():
            raise DataError(f"--src {src} is not a folder")
        split = make_split(duplicate_groups(read_tosses(Path(src))), int(d["test"]), int(d["valid"]))
        ids = training_ids(split, int(d["tosses"]), 0)
        real = import_stage(Path(src), out / "data", {"train": ids, **({"valid": split["valid"]} if split["valid"] else {})})
        test = import_stage(Path(src), out / "test", {"test": split["test"]})
        if kind == "contactnets":
            ds = Dataset(real)
        else:
            from pipelines.common import Costs
            from pipelines.engine_pretrain import synthetic_stage
            from pipelines.real_cubes_baselines import fit_stage
            fit = fit_stage(out / "fit_mujoco.json", real, ids, "mujoco", int(d["fit_budget"]), 0,
                            int(d["fit_tosses"]), Costs(out / "costs.json"))
            ds = synthetic_stage(out / "data_mujoco", real, "mujoco", fit["params"], int(d["synthetic"]), 0,
                                 int(d["real_copies"]))
        _check_fingerprint(recipe, ds)
        return ds, test
    raise DataError(f"recipe {recipe.name}: unknown data kind {kind!r} (datagen, tilted_drops, contactnets, "
                    "contactnets_mujoco)")


def train_recipe(recipe: Recipe, out: Path, data: Path | None = None, src: Path | None = None,
                 workers: int = 2) -> tuple[Path, Path | None, Path | None, Path]:
    """Every run of the recipe in order; returns the model's checkpoint (the last run's that is not
    a contact network's), its contact network's (the last contact run's, or None), the test data
    and the training data."""
    from pipelines.common import say, train_stage
    ds, test = data_stage_of(recipe, out, data, src, workers)
    previous = ckpt = contact = None
    for k, r in enumerate(recipe.runs):
        say(f"recipe {recipe.name}: run {k + 1} of {len(recipe.runs)}, {r.name} ({r.steps} steps, seed {r.seed}"
            f"{', the contact network' if r.contact else ''})")
        trained = train_stage(ds.root, out / "runs" / r.name, recipe.model.removeprefix("gns_"),
                              run_overrides(r, previous))
        previous = trained.parent
        if r.contact:
            contact = trained
        else:
            ckpt = trained
    return ckpt, contact, test, ds.root


def score(recipe: Recipe, out: Path, ckpt: Path, test: Path | None, contact: Path | None = None,
          train_data: Path | None = None) -> dict | None:
    """The exported model scored as each zoo card says (its rollout options, on the recipe's test
    data), or with the default options for a recipe outside the zoo; None, the model exported
    unscored, when the data has no test scenes."""
    from datagen.shards import Dataset
    from pipelines.common import say
    from gns import zoo
    from gns.spec import RolloutOptions
    from gns.zoo import export_model
    from gns.evaluate import write_json
    model = export_model(ckpt, out / "model.pt", overwrite=True, contact=contact,
                         between=train_data if recipe.between else None)
    if test is not None and Dataset(test).num_scenes("test") == 0:
        say(f"model: {model}; not scored: {test} has no test scenes")
        return None
    rows = {}
    for name in recipe.zoo or ("",):
        card = zoo.card(name) if name else None
        options = card.options if card else RolloutOptions()
        if recipe.data.get("kind") == "tilted_drops":
            from pipelines.diagnostic_45 import run as diagnostic
            r = diagnostic("quick", out / "diagnostic", model, 0, "all", f"python -m pipelines.recipe {recipe.name}")
            scores = {f"{path} {v}": f"{a}/{b}" for path, row in r["totals"].items() for v, (a, b) in row.items()}
        else:
            from gns.evaluate import evaluate_run
            at_data_rate = bool(card and card.data.get("eval", {}).get("at_data_rate"))
            results, *_ = evaluate_run(model, test, "test", options=options, progress=False,
                                       at_data_rate=at_data_rate)
            scores = {k: round(results[k], 3) for k in METRICS}
        rows[name or "default options"] = {"options": options.to_dict(), "scores": scores,
                                           "card": card.data.get("scores", [{}])[0] if card else None}
    results = {"recipe": recipe.name, "model": str(model), "test_data": str(test), "rows": rows}
    write_json(out / "results.json", results)
    where = f"`{test}`" if test is not None else "the 45-degree cases of pipelines.diagnostic_45 (quick)"
    lines = [f"# Recipe {recipe.name}", "", f"Model: `{model}`; scored on {where}.", "",
             "| rolled out as | scores | the card's |", "|---|---|---|"]
    for name, row in rows.items():
        c = row["card"] or {}
        card_scores = ", ".join(f"{k} {v}" for k, v in c.items() if k in METRICS or k == "sides") or "-"
        lines.append(f"| {name} | {', '.join(f'{k} {v}' for k, v in row['scores'].items())} | {card_scores} |")
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return results


def main(argv=None) -> int:
    from pipelines.common import guarded, say
    ap = argparse.ArgumentParser(prog="python -m pipelines.recipe", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recipe", nargs="?", help="a recipe name (configs/recipes/NAME.toml) or a .toml file")
    ap.add_argument("--out", type=Path, help="output folder (default runs/recipe_NAME)")
    ap.add_argument("--data", type=Path, help="train on this dataset instead of making the recipe's")
    ap.add_argument("--src", type=Path, help="the real cube recipes: the ContactNets folder holding tosses_processed/")
    ap.add_argument("--workers", type=int, default=2, help="datagen worker processes (default 2)")
    ap.add_argument("--list", action="store_true", help="list the recipes and what they train")
    a = ap.parse_args(argv)
    if a.list or not a.recipe:
        for name in recipe_names():
            r = load_recipe(name)
            print(f"{name}: {len(r.runs)} runs, {sum(x.steps for x in r.runs)} steps; zoo {', '.join(r.zoo) or '-'}; "
                  f"{r.cost}")
        return 0

    def stages():
        recipe = load_recipe(a.recipe)
        out = a.out or Path("runs") / f"recipe_{recipe.name}"
        ckpt, contact, test, train_data = train_recipe(recipe, out, a.data, a.src, a.workers)
        if score(recipe, out, ckpt, test, contact, train_data) is not None:
            say(f"report: {out / 'report.md'}")
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
