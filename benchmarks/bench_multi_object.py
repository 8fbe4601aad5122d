"""Learned rollouts of scenes of several objects against PyBullet on the same scenes, by the number
of objects a scene: cost per simulated second and per step, the contacts between objects, and the
throughput ratio of all scenes batched, in one run.

PyBullet simulates each scene again from the dataset's config and seed (build + step, one scene at
a time, as the data was made); the model rolls the scenes of each object count out batched, and
then all scenes in one batch, with its card's rollout options (or the flags). Rounds alternate
PyBullet and the model, best of --repeats, one thread. "touching pairs" is the mean number of
object pairs a frame whose bounding spheres touch in the truth: the contacts a step must handle.

    python benchmarks/bench_multi_object.py --run movi_a_multi --data data/multi_test --plot cost.png
    python benchmarks/bench_multi_object.py --run RUN --data DIR --keep-apart --compile --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent.parent), str(Path(__file__).resolve().parent)]

from bench_datagen import step_only  # noqa: E402
from bench_learned_vs_physics import pybullet_specs  # noqa: E402
from gns.checkpoint import default_options, load_simulator, checkpoint_of  # noqa: E402
from gns.evaluate import load_split  # noqa: E402
from gns.metrics import bounding_gaps  # noqa: E402
from gns.network import HISTORY  # noqa: E402
from gns.evaluate import rollout_scenes  # noqa: E402


def touching_pairs(sc, meshes) -> float:
    """Mean number of object pairs a frame whose bounding spheres touch, in the truth."""
    upper = np.triu(np.ones((sc.num_objects, sc.num_objects), bool), 1)
    return float((bounding_gaps(sc, meshes)[:, upper] < 0).sum(axis=1).mean())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="run folder, checkpoint or zoo model (its card's options)")
    p.add_argument("--data", required=True, help="a datagen toss dataset of several objects a scene")
    p.add_argument("--split", default="test")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--keep-apart", action=argparse.BooleanOptionalAction, help="override the options' keep_apart")
    p.add_argument("--compile", action=argparse.BooleanOptionalAction,
                   help="override the options' compile (the network and, for face edges, the triangle distances)")
    p.add_argument("--json")
    p.add_argument("--plot", help="PNG: cost per step against objects a scene, both simulators")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    options = default_options(a.run)
    for key in ("keep_apart", "compile"):
        if getattr(a, key) is not None:
            options = options.replace(**{key: getattr(a, key)})
    sim, saved = load_simulator(checkpoint_of(a.run), "cpu", options)
    ds, scenes = load_split(a.data, a.split, None, saved["spec"]["frame_rate"])
    if ds.stride != 1:
        raise SystemExit("error: the model steps at a stride of the data's frames; give data at its rate")
    cfg, specs = pybullet_specs(ds, scenes, a.split)
    groups = defaultdict(list)
    for i, sc in enumerate(scenes):
        groups[sc.num_objects].append(i)
    jobs = [(str(n), idx) for n, idx in sorted(groups.items())] + [("all", list(range(len(scenes))))]
    best = {name: {"pybullet": np.inf, "gns": np.inf} for name, _ in jobs}
    for name, idx in jobs:                                   # warm-up: caches, autocast's measurement
        rollout_scenes(sim, [scenes[i] for i in idx[:2]], ds.meshes, ds.frame_rate, progress=False)
    for _ in range(a.repeats):
        for name, idx in jobs:
            t0 = time.perf_counter()
            for i in idx:
                step_only(specs[i], cfg)
            best[name]["pybullet"] = min(best[name]["pybullet"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            rollout_scenes(sim, [scenes[i] for i in idx], ds.meshes, ds.frame_rate, progress=False)
            best[name]["gns"] = min(best[name]["gns"], time.perf_counter() - t0)
    rows = []
    for name, idx in jobs:
        steps = sum(scenes[i].num_frames - HISTORY for i in idx)       # model steps, summed over scenes
        seconds = sum((scenes[i].num_frames - 1) / ds.frame_rate for i in idx)
        simulated = sum((scenes[i].num_frames - HISTORY) / ds.frame_rate for i in idx)
        pb, gn = best[name]["pybullet"], best[name]["gns"]
        rows.append({"objects": name, "scenes": len(idx),
                     "touching_pairs": float(np.mean([touching_pairs(scenes[i], ds.meshes) for i in idx])),
                     "pybullet_ms_per_simulated_s": 1e3 * pb / seconds, "gns_ms_per_simulated_s": 1e3 * gn / simulated,
                     "gns_ms_per_scene_step": 1e3 * gn / steps,
                     "x_pybullet": (pb / seconds) / (gn / simulated)})
    print(f"{len(scenes)} {a.split} scenes of {a.data}; model {a.run} with {options.to_dict()}; one thread, "
          f"best of {a.repeats}; each group batched")
    print("| objects | scenes | touching pairs a frame | PyBullet ms per simulated s | GNS ms per simulated s | "
          "GNS ms per scene-step | x PyBullet throughput |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['objects']} | {r['scenes']} | {r['touching_pairs']:.2f} | {r['pybullet_ms_per_simulated_s']:.1f} | "
              f"{r['gns_ms_per_simulated_s']:.1f} | {r['gns_ms_per_scene_step']:.2f} | {r['x_pybullet']:.2f} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"run": a.run, "data": a.data, "options": options.to_dict(),
                                            "repeats": a.repeats, "rows": rows}, indent=2) + "\n")
    if a.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        per = [r for r in rows if r["objects"] != "all"]
        n = [int(r["objects"]) for r in per]
        fig, ax = plt.subplots(figsize=(5.5, 3.6))
        ax.plot(n, [r["pybullet_ms_per_simulated_s"] for r in per], "o-", label="PyBullet (one scene at a time)")
        ax.plot(n, [r["gns_ms_per_simulated_s"] for r in per], "s-", label=f"{a.run} (scenes of a count batched)")
        for r, x in zip(per, n):
            ax.annotate(f"{r['touching_pairs']:.1f}", (x, r["gns_ms_per_simulated_s"]), textcoords="offset points",
                        xytext=(0, 6), ha="center", fontsize=7)
        ax.set_xlabel("objects a scene (labels: touching pairs a frame)")
        ax.set_ylabel("ms of wall clock per simulated s, per scene")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(a.plot, dpi=120)
        print(f"plot: {a.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
