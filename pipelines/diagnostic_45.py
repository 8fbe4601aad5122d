"""The 45-degree diagnostic (the paper's Fig. 3): does a GNS topple a cube to PyBullet's side?

    python -m pipelines.diagnostic_45 --preset tiny|quick [--run RUN_OR_PT] [--out DIR] [--fresh]
        [--shape cube|beveled_cube|all] [--variants none,d1]

A cube (datagen shape `cube`, or MOVi-A's `beveled_cube`; `metal`) stands on one edge, tilted by an
angle about it. Below 45 degrees its centre is over its own face and it falls back onto it (side
+1); above 45 it falls over the edge (side -1). The angles 43, 44, 44.5, 44.75, 45.25, 45.5, 46,
47 form mirrored pairs 45 -+ d (d = 2, 1, 0.5, 0.25). Every case (pipelines.diagnostic_45_cases):
each shape at both MOVi-A sizes (0.7, 1.4), released at rest on its edge or dropped onto it from
0.5 and 1 size above the floor: 12 cases of 8 angles for both shapes. PyBullet simulates each
(datagen's settings, 12 fps, 240 Hz, 36 frames = 3 s); the GNS rolls each out from PyBullet's
first 3 frames (as `gns eval` and `gns rollout` do) and through the Python API from the release
pose, at each rollout variant (default: --symmetrize none, one network call a step, and d1, the
average with the mirror image in x, two). The side is the sign of the final centre x relative to
the edge (datagen.tilted.side; 0 if it has not fallen).

Stages (each skipped on rerun when its output is complete):
  drops    the drop scenes of every case simulated by PyBullet, a dataset in OUT/drops
  data     (no --run) training scenes (datagen.tilted.training_scene), in OUT/data
  train    (no --run) gns.train on the preset's model, in OUT/run
  eval     sides per case, input and variant: OUT/results.json, OUT/report.md (the table, a
           row a case), OUT/plots/fig3.png (the cube of size 1.4 on its edge, centre x against
           time, GNS dashed beside PyBullet solid) and OUT/plots/cases_VARIANT.png (every case)

Presets:
  tiny   smoke test: 8+2 training scenes of the cube, the tiny model, 40 steps (seconds)
  quick  the zoo recipe (configs/recipes/diagnostic_45.toml): its data (cube and beveled cube,
         drops from up to one size, MOVi-A tosses), its model and training

--run evaluates an existing run folder, .pt checkpoint or zoo name instead of training.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from plumbing import DataError, atomic_file, atomic_folder
from datagen.scenes import load_config
from datagen.output import plan
from datagen.toss import metadata
from datagen.scenes import get_shape
from datagen.shards import Dataset, write_metadata, write_shard
from datagen.toss import simulate
from datagen.tilted import tilted_scene, training_scene
from gns.checkpoint import checkpoint_of
from gns.evaluate import write_json
from gns.spec import ModelSpec
from gns.checkpoint import read_checkpoint
from pipelines import diagnostic_45_cases as cases_
from pipelines.common import finished_dataset, guarded, say, train_stage

ANGLES = cases_.ANGLES
FRAMES = 36   # 3 s at 12 fps: PyBullet's cubes have fallen by frame 30, dropped from 1 size too
MATERIAL = "metal"
VERSION = 5  # of results.json: older results are recomputed
sides = cases_.sides

PRESETS = {
    "tiny": dict(counts={"train": 8, "valid": 2}, model="tiny", steps=40),
    "quick": dict(recipe="diagnostic_45"),
}


def scene_config(shapes) -> dict:
    """datagen's MOVi-A config with these shapes (a name or a list) and FRAMES frames a scene."""
    names = [shapes] if isinstance(shapes, str) else list(shapes)
    return load_config(sets=[f"scene.frames={FRAMES}", f"scene.shapes={json.dumps(names)}"])


def write_dataset(out: Path, cfg: dict, seed: int, specs: dict[str, list], extra: dict) -> Dataset:
    """Simulate scene specs {split: [SceneSpec]} into a dataset folder, written whole under a
    temporary name and renamed, so an interrupted stage leaves nothing that looks finished."""
    counts = {s: len(v) for s, v in specs.items()}
    meshes = {n: (get_shape(n).vertices, get_shape(n).faces) for n in cfg["scene"]["shapes"]}
    with atomic_folder(out) as tmp:
        tasks = plan(counts, max(counts.values()))
        for t in tasks:
            scenes = [simulate(spec, cfg) for spec in specs[t.split]]
            write_shard(tmp / t.name, scenes, meshes, attrs={"split": t.split, "shard": t.shard, "seed": seed})
        meta = metadata(cfg, seed, counts, tasks, complete=True)
        meta.update(generator="pipelines.diagnostic_45", diagnostic_45=extra)
        write_metadata(tmp, meta)
    return Dataset(out)


def dataset_stage(out: Path, what: str, extra: dict, make) -> Dataset:
    ds = finished_dataset(out, "diagnostic_45", extra, what)
    if ds is not None:
        return ds
    say(f"{what}: simulating into {out}")
    return make()


def drops_stage(out: Path, shapes) -> tuple[Dataset, list[dict]]:
    """Every case of these shapes (diagnostic_45_cases.cases), 8 angles each, case after case."""
    cfg = scene_config(shapes)
    case_list = cases_.cases(shapes)
    extra = {"kind": "drops", "angles": list(ANGLES), "cases": case_list, "material": MATERIAL}
    specs = [tilted_scene(cfg, a, index=len(ANGLES) * k + i, shape=c["shape"], size=c["size"], material=MATERIAL,
                          height=c["height"] * float(cfg["sizes"][c["size"]]))
             for k, c in enumerate(case_list) for i, a in enumerate(ANGLES)]
    ds = dataset_stage(out, "drops", extra, lambda: write_dataset(out, cfg, 0, {"test": specs}, extra))
    return ds, [{**c, "scale": float(cfg["sizes"][c["size"]])} for c in case_list]


def training_data_stage(out: Path, counts: dict, seed: int, shapes=("cube",), max_heights=(0.05,)) -> Dataset:
    """Training scenes (datagen.tilted.training_scene) of these shapes, each drop's lowest vertex
    up to one of `max_heights` x its size above the floor."""
    shapes, max_heights = tuple(shapes), tuple(float(h) for h in max_heights)
    cfg = scene_config(shapes)
    extra = {"kind": "training", "counts": counts, "seed": seed, "drop_fraction": 0.5}
    # recorded only where they are not the first recipe's, whose data keeps its metadata (and fingerprint)
    if shapes != ("cube",):
        extra["shapes"] = list(shapes)
    if max_heights != (0.05,):
        extra["max_heights"] = list(max_heights)
    return dataset_stage(out, "data", extra, lambda: write_dataset(
        out, cfg, seed, {s: [training_scene(cfg, seed, s, i, max_heights=max_heights) for i in range(n)]
                         for s, n in counts.items()}, extra))


def evaluate(ckpt: Path, drops: Dataset, case_list: list[dict], out: Path, variants) -> dict:
    saved = read_checkpoint(ckpt)
    path = out / "results.json"
    key = {"version": VERSION, "checkpoint": str(ckpt), "checkpoint_step": int(saved["step"]), "angles": list(ANGLES),
           "cases": case_list, "variants": list(variants)}
    if path.exists():
        old = json.loads(path.read_text())
        if all(old.get(k) == v for k, v in key.items()):
            say("eval: results.json matches the checkpoint, skipping")
            return old
    scored, predicted = cases_.score(ckpt, drops, case_list, variants, say)
    results = {**key, "material": MATERIAL, "frames": FRAMES,
               "trained_shapes": list(ModelSpec.from_dict(saved["spec"]).shapes), **scored}
    results["totals"] = cases_.totals(results)
    truth, n = drops.load("test"), len(ANGLES)
    panels = {v: [(f"{c['shape']} {c['scale']:g} {c['start']}, {v}", predicted[v][k * n:(k + 1) * n],
                   truth[k * n:(k + 1) * n]) for k, c in enumerate(case_list)] for v in variants}
    main = next((k for k, c in enumerate(case_list) if c["size"] == "large" and c["start"] == "edge"), 0)
    results["plot"] = str(cases_.plot(out / "plots" / "fig3.png", [panels[v][main] for v in variants], drops.dt)
                          .relative_to(out))
    for v in variants:
        cases_.plot(out / "plots" / f"cases_{v.replace(' ', '_')}.png", panels[v], drops.dt, columns=3)
    write_json(path, results)
    return results


def report(out: Path, r: dict, command: str) -> Path:
    lines = [f"# 45-degree diagnostic (Fig. 3): `{r['checkpoint']}` (step {r['checkpoint_step']})", "",
             f"Made by `{command}`. Each shape ({r['material']}) at each size stands on one edge, tilted by the angle "
             f"about it ({', '.join(f'{a:g}' for a in r['angles'])} degrees), released at rest there or dropped onto "
             f"it; PyBullet 240 Hz recorded at 12 fps for {r['frames']} frames is the truth. Inputs: `data` PyBullet's "
             "first 3 frames (gns eval, gns rollout); `API` gns.load(...).rollout from the release pose (the edge: "
             "history= the pose held still; a drop: velocities 0, free flight backwards); `API held` a drop from "
             "history= the pose held still. Right sides of 8 angles per case:", "",
             *cases_.table_lines(r), "", "Angles on the wrong side (the GNS's side: +1 back, -1 over, 0 not fallen):",
             "", *cases_.wrong_lines(r), ""]
    if r["outside_training"]:
        lines += [f"Outside training: {'; '.join(r['outside_training'])}.", ""]
    lines += [f"![Fig. 3]({r['plot']})"]
    path = out / "report.md"
    with atomic_file(path, mode=0o644) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def run(preset: str, out: Path, run_path: Path | None, seed: int, shape: str, command: str,
        sets: list[str] = (), variants=cases_.DEFAULT_VARIANTS) -> dict:
    if run_path is not None:
        read_checkpoint(checkpoint_of(run_path))  # a missing or bad checkpoint fails first, one line
    unknown = [v for v in variants if v not in cases_.VARIANTS]
    if unknown:
        raise DataError(f"--variants: unknown {unknown[0]!r}; known: {', '.join(cases_.VARIANTS)}")
    out.mkdir(parents=True, exist_ok=True)
    drops, case_list = drops_stage(out / "drops", cases_.SHAPES if shape == "all" else (shape,))
    if run_path is None:
        p = PRESETS[preset]
        if "recipe" in p:
            from pipelines.recipe import load_recipe
            recipe = load_recipe(p["recipe"])
            d = recipe.data
            data = training_data_stage(out / "data", {"train": int(d["train"]), "valid": int(d["valid"])}, seed,
                                       d.get("shapes", ("cube",)), d.get("max_heights", (0.05,)))
            first = recipe.runs[0]   # the recipe's one stage
            ckpt = train_stage(data.root, out / "run", recipe.model.removeprefix("gns_"),
                               [*first.overrides, f"train.steps={first.steps}", f"train.seed={seed}", *sets])
        else:
            data = training_data_stage(out / "data", p["counts"], seed)
            ckpt = train_stage(data.root, out / "run", p["model"], [f"train.steps={p['steps']}", f"train.seed={seed}", *sets])
    else:
        ckpt = checkpoint_of(run_path)
    results = evaluate(ckpt, drops, case_list, out, list(variants))
    say(f"report: {report(out, results, command)}")
    for line in cases_.table_lines(results):
        print(line)
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.diagnostic_45", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    ap.add_argument("--run", type=Path, help="evaluate this run folder, .pt checkpoint or zoo name instead of training")
    ap.add_argument("--shape", choices=["all", *cases_.SHAPES], default="all",
                    help="shapes dropped (default all: the cube and the beveled cube)")
    ap.add_argument("--variants", default=",".join(cases_.DEFAULT_VARIANTS),
                    help=f"rollout variants, comma-separated, of {', '.join(cases_.VARIANTS)} (default none,d1)")
    ap.add_argument("--out", type=Path, help="output folder (default runs/diagnostic_45_<preset or run name>)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fresh", action="store_true", help="delete the output folder first instead of resuming")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="training config overrides after the preset's (gns train --set), e.g. augment.mirror=false")
    a = ap.parse_args(argv if argv is not None else sys.argv[1:])
    name = a.preset
    if a.run is not None:
        # a run folder or its latest.pt is named by the folder holding the run (runs/X/run -> X)
        path = a.run.resolve()
        path = path.parent if path.suffix == ".pt" and path.stem == "latest" else path
        name = path.parent.name if path.name == "run" else path.stem
    out = a.out or Path("runs") / f"diagnostic_45_{name}"
    if a.fresh and out.exists():
        shutil.rmtree(out)
    command = "python -m pipelines.diagnostic_45 " + " ".join(argv if argv is not None else sys.argv[1:])
    variants = [v.strip() for v in a.variants.split(",") if v.strip()]
    return guarded(lambda: run(a.preset, out, a.run, a.seed, a.shape, command, a.set, variants))


if __name__ == "__main__":
    sys.exit(main())
