"""The 45-degree diagnostic (the paper's Fig. 3): does a GNS topple a cube to PyBullet's side?

    python -m pipelines.diagnostic_45 --preset tiny|quick [--run RUN_OR_PT] [--out DIR] [--fresh]

A cube (datagen shape `cube`, the MOVi-A config's `large` size 1.4, `metal`) stands on one edge,
tilted by an angle about it, released from rest. Below 45 degrees its centre is over its own
face and it falls back onto it (side +1); above 45 it falls over the edge (side -1). The angles
43, 44, 44.5, 44.75, 45.25, 45.5, 46, 47 form mirrored pairs 45 -+ d (d = 2, 1, 0.5, 0.25).
PyBullet simulates each drop (datagen's settings, 12 fps, 240 Hz, 36 frames = 3 s); the GNS
rolls out from the first 3 frames, plain and with --symmetrize's averaging over the floor's
mirror symmetries (gns.simulator.LearnedSimulator.symmetrize). The side is the sign of the
final centre x relative to the edge (datagen.tilted.side; 0 if it has not fallen).

Stages (each skipped on rerun when its output is complete):
  drops    the 8 drop scenes simulated by PyBullet, a dataset in OUT/drops
  data     (no --run) training scenes: half tilted cube drops (tilt 0-90 deg, half of them
           within a few degrees of 45; random heading, place, size, material), half MOVi-A
           cube tosses, all simulated by datagen, in OUT/data
  train    (no --run) gns.train on the preset's model, in OUT/run
  eval     sides per angle, plain, symmetrized (floor mirrors) and symmetrized over the cube's
           24 body frames too (--body-frames): OUT/results.json, OUT/report.md,
           OUT/plots/fig3.png (centre x against time, GNS dashed beside PyBullet solid)

Presets:
  tiny   smoke test: 8+2 training scenes, the tiny model, 40 steps (seconds)
  quick  400+20 training scenes, the CPU model (L=5, latent 64), 24000 steps: ~10 min on one
         core (8-vertex cubes train at ~40 steps/s)

--run evaluates an existing run folder or .pt checkpoint (e.g. tests/data/gns_movi_a_small.pt)
instead of training; --shape beveled_cube drops MOVi-A's beveled cube instead (for models
trained without `cube`).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from plumbing import atomic_file, atomic_folder
from datagen.scenes import load_config
from datagen.generate import metadata, plan
from datagen.scenes import get_shape
from datagen.shards import Dataset, write_metadata, write_shard
from datagen.simulate import simulate
from datagen.tilted import side, tilted_scene, training_scene
from gns.checkpoint import checkpoint_of
from gns.evaluate import evaluate_run, write_json
from gns.spec import RolloutOptions
from gns.rollout import rollout_scenes
from gns.spec import ModelSpec
from gns.checkpoint import load_model, read_checkpoint
from pipelines.common import finished_dataset, guarded, say, train_stage

ANGLES = (43.0, 44.0, 44.5, 44.75, 45.25, 45.5, 46.0, 47.0)
FRAMES = 36   # 3 s at 12 fps: PyBullet's 44.75-degree cube has fallen by frame 30
SIZE, MATERIAL = "large", "metal"
VERSION = 4  # of results.json: older results are recomputed
# rollouts compared: (name, averaged over the floor's mirrors, and over the cube's 24 body frames)
VARIANTS = (("plain", False, False), ("symmetrized", True, False), ("body frames", True, True))

PRESETS = {
    "tiny": dict(counts={"train": 8, "valid": 2}, model="tiny", steps=40),
    # mirror and body-symmetry augmentation: with --body-frames rollouts, 8 of 8 (docs/results.md)
    "quick": dict(counts={"train": 400, "valid": 20}, model="cpu", steps=24000,
                  train=("augment.mirror=true", "augment.body_symmetry=true")),
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


def drops_stage(out: Path, shape: str, angles=ANGLES) -> Dataset:
    cfg = scene_config(shape)
    extra = {"kind": "drops", "angles": list(angles), "shape": shape, "size": SIZE, "material": MATERIAL}
    specs = [tilted_scene(cfg, a, index=i, shape=shape, size=SIZE, material=MATERIAL) for i, a in enumerate(angles)]
    return dataset_stage(out, "drops", extra, lambda: write_dataset(out, cfg, 0, {"test": specs}, extra))


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


def sides(pred: list, true: list, angles) -> dict:
    """Per angle: PyBullet's side, the GNS's, agreement; and the mirrored pairs' check."""
    rows = []
    for a, p, t in zip(angles, pred, true, strict=True):
        s = float(t.scale[0])
        rows.append({"angle": a, "pybullet": side(t.positions, s), "gns": side(p.positions, s),
                     "pybullet_final_x": float(t.positions[-1, 0, 0]), "gns_final_x": float(p.positions[-1, 0, 0])})
        rows[-1]["agree"] = rows[-1]["pybullet"] == rows[-1]["gns"] != 0
    by_angle = {r["angle"]: r for r in rows}
    pairs = []
    for a in angles:
        b = 90.0 - a
        if a < 45 and b in by_angle:
            lo, hi = by_angle[a], by_angle[b]
            pairs.append({"d": 45.0 - a, "angles": [a, b],
                          "pybullet_mirrored": lo["pybullet"] == -hi["pybullet"] != 0,
                          "gns_mirrored": lo["gns"] == -hi["gns"] != 0})
    return {"rows": rows, "pairs": pairs, "agree": sum(r["agree"] for r in rows), "total": len(rows)}


def mirrored(sc):
    """The scene mirrored in x (x -> -x): the exact mirror image, object labels and mesh kept."""
    flip = np.array([-1.0, 1.0, 1.0])
    return dataclasses.replace(sc, positions=sc.positions * flip, velocities=sc.velocities * flip,
                               quaternions=sc.quaternions * np.array([1.0, 1.0, -1.0, -1.0]),
                               angular_velocities=sc.angular_velocities * -flip,
                               attrs={**sc.attrs, "mirrored_x": True})


def mirror_check(sim, drops: Dataset, true: list, angles, table: dict) -> None:
    """Add to each pair the GNS side of the exact x-mirror of the 45 - d scene's PyBullet input
    and how far its vertices are from the 45 + d scene's (as point sets, over the 3 input
    frames). With --symmetrize the rollout is exactly equivariant, so the copy goes to minus the
    45 - d side. The copy and the 45 + d scene are the same points in different body frames
    (turned 90 degrees about the cube's own axis, a symmetry of the cube that the rest-position
    features do not share): where their sides differ, the body frame decides, not the angle."""
    index = {a: i for i, a in enumerate(angles)}
    lows = [p["angles"][0] for p in table["pairs"]]
    pred = rollout_scenes(sim, [mirrored(true[index[a]]) for a in lows], drops.meshes, drops.frame_rate,
                          progress=False)
    for p, sc in zip(table["pairs"], pred):
        p["gns_side_of_mirrored_copy"] = side(sc.positions, float(sc.scale[0]))
        p["input_mirror_difference"] = _vertex_set_distance(
            mirrored(true[index[p["angles"][0]]]), true[index[p["angles"][1]]], drops.meshes)


def _vertex_set_distance(a, b, meshes) -> float:
    """Largest distance from a vertex of scene a to the nearest of scene b, over the 3 input
    frames: 0 when the GNS gets the same points, whatever the vertex labels."""
    from gns.geometry import pose_to_vertices
    rest = meshes[a.shape[0]][0]
    worst = 0.0
    for t in range(3):
        va = pose_to_vertices(a.positions[t, 0], a.quaternions[t, 0], float(a.scale[0]), rest)
        vb = pose_to_vertices(b.positions[t, 0], b.quaternions[t, 0], float(b.scale[0]), rest)
        worst = max(worst, float(np.linalg.norm(va[:, None] - vb[None], axis=-1).min(1).max()))
    return worst


def plot(path: Path, curves: dict, true: list, angles, dt: float) -> Path:
    """Fig. 3 as a time series: centre x / size against time, PyBullet solid, GNS dashed."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(5.5 * len(curves), 4.2))
    FigureCanvasAgg(fig)
    cmap = colormaps["coolwarm"]
    for k, (title, pred) in enumerate(curves.items()):
        ax = fig.add_subplot(1, len(curves), k + 1)
        for i, (a, p, t) in enumerate(zip(angles, pred, true)):
            c = cmap(i / max(len(angles) - 1, 1))
            time = np.arange(t.num_frames) * dt
            s = float(t.scale[0])
            ax.plot(time, t.positions[:, 0, 0] / s, color=c, lw=1.6, label=f"{a:g} deg")
            ax.plot(time[:p.num_frames], p.positions[:, 0, 0] / s, color=c, lw=1.6, ls="--")
        ax.axhline(0, color="gray", lw=0.6)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("centre x from the edge [sizes]")
        ax.set_title(f"{title}: PyBullet solid, GNS dashed", fontsize=9)
        if k == 0:
            ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def evaluate(ckpt: Path, drops: Dataset, out: Path, shape: str) -> dict:
    saved = read_checkpoint(ckpt)
    angles = drops.meta["diagnostic_45"]["angles"]
    path = out / "results.json"
    if path.exists():
        old = json.loads(path.read_text())
        if old.get("checkpoint") == str(ckpt) and old.get("checkpoint_step") == int(saved["step"]) \
                and old.get("angles") == angles and old.get("shape") == shape and old.get("version") == VERSION:
            say("eval: results.json matches the checkpoint, skipping")
            return old
    results = {"version": VERSION, "checkpoint": str(ckpt), "checkpoint_step": int(saved["step"]), "angles": angles, "shape": shape,
               "size": float(drops.meta["config"]["sizes"][SIZE]), "material": MATERIAL, "frames": FRAMES,
               "trained_shapes": list(ModelSpec.from_dict(saved["spec"]).shapes)}
    curves = {}
    for name, sym, body in VARIANTS:
        say(f"eval: rolling out the drops ({name})")
        res, pred, true, _ = evaluate_run(ckpt, drops.root, "test", symmetrize=sym, body_frames=body, progress=False)
        results[name] = sides(pred, true, angles)
        sim, _ = load_model(saved, options=RolloutOptions(symmetrize=sym, body_frames=body))
        mirror_check(sim, drops, true, angles, results[name])
        results["outside_training"] = res["outside_training"]
        curves[name] = pred
    results["plot"] = str(plot(out / "plots" / "fig3.png", curves, true, angles, drops.dt).relative_to(out))
    write_json(path, results)
    return results


def _side_name(s: int) -> str:
    return {1: "+1 back", -1: "-1 over", 0: "0 none"}[s]


def report(out: Path, r: dict, command: str) -> Path:
    lines = [f"# 45-degree diagnostic (Fig. 3): `{r['checkpoint']}` (step {r['checkpoint_step']})", "",
             f"Made by `{command}`. A `{r['shape']}` of size {r['size']:g} ({r['material']}) on one edge, tilted by "
             f"the angle about it, released from rest; PyBullet 240 Hz recorded at 12 fps for {r['frames']} frames, "
             "the GNS rolled out from the first 3. Side: +1 back onto the lifted face (statics: below 45 degrees), "
             "-1 over the edge (above 45), 0 not fallen.", ""]
    if r["outside_training"]:
        lines += [f"Outside training: {'; '.join(r['outside_training'])}.", ""]
    for name, *_ in VARIANTS:
        x = r[name]
        lines += [f"## {name.capitalize()} rollout: {x['agree']} of {x['total']} on PyBullet's side", "",
                  "| angle | PyBullet | GNS | agree | final x PyBullet | final x GNS |", "|---|---|---|---|---|---|"]
        for row in x["rows"]:
            lines.append(f"| {row['angle']:g} | {_side_name(row['pybullet'])} | {_side_name(row['gns'])} | "
                         f"{'yes' if row['agree'] else 'NO'} | {row['pybullet_final_x']:.3f} | {row['gns_final_x']:.3f} |")
        lines += ["", "Mirrored pairs 45 - d / 45 + d (should land on opposite sides): " + ", ".join(
            f"d={p['d']:g}: PyBullet {'yes' if p['pybullet_mirrored'] else 'no'}, "
            f"GNS {'yes' if p['gns_mirrored'] else 'no'}" for p in x["pairs"]) + ".", "",
                  "GNS side of the exact x-mirror of the 45 - d scene's input (PyBullet's 45 + d side is -1): " +
                  ", ".join(f"d={p['d']:g}: {p['gns_side_of_mirrored_copy']:+d}" for p in x["pairs"]) +
                  " (the copy's input vertices are within " +
                  f"{max(p['input_mirror_difference'] for p in x['pairs']):.2g} of the 45 + d scene's).", ""]
    lines += [f"![Fig. 3]({r['plot']})"]
    path = out / "report.md"
    with atomic_file(path, mode=0o644) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def run(preset: str, out: Path, run_path: Path | None, seed: int, shape: str, command: str,
        sets: list[str] = ()) -> dict:
    if run_path is not None:
        read_checkpoint(checkpoint_of(run_path))  # a missing or bad checkpoint fails first, one line
    out.mkdir(parents=True, exist_ok=True)
    drops = drops_stage(out / "drops", shape)
    if run_path is None:
        p = PRESETS[preset]
        data = training_data_stage(out / "data", p["counts"], seed)
        ckpt = train_stage(data.root, out / "run", p["model"],
                           [f"train.steps={p['steps']}", f"train.seed={seed}", *p.get("train", ()), *sets])
    else:
        ckpt = checkpoint_of(run_path)
    results = evaluate(ckpt, drops, out, shape)
    say(f"report: {report(out, results, command)}")
    for name, *_ in VARIANTS:
        x = results[name]
        print(f"{name}: {x['agree']}/{x['total']} on PyBullet's side; " + ", ".join(
            f"{row['angle']:g}: {row['pybullet']:+d}/{row['gns']:+d}" for row in x["rows"]))
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.diagnostic_45", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    ap.add_argument("--run", type=Path, help="evaluate this run folder or .pt checkpoint instead of training")
    ap.add_argument("--shape", choices=["cube", "beveled_cube"], default="cube", help="shape dropped (default cube)")
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
    return guarded(lambda: run(a.preset, out, a.run, a.seed, a.shape, command, a.set))


if __name__ == "__main__":
    sys.exit(main())
