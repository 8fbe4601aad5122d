"""Training speed of the GNS presets: steps/s, graphs/s, and achieved FLOP rate vs matmul peak.

Presets (configs/gns_<name>.toml): the FLOPs are those of the Linear layers (2 per multiply-add),
counted analytically from the batch's node and edge counts; a training step is taken as 3x the
forward pass (backward ~2x). Peak is this machine's measured float32 rate for a 1024 x 1024
matmul with the same threads, timed in the same run, so the fraction says how well the small
MLPs use the hardware.

    python benchmarks/bench_train.py                      # synthetic MOVi-like tosses
    python benchmarks/bench_train.py --data data/movi_a   # a real dataset's train split
    python benchmarks/bench_train.py --autocast --rounds 3   # float32 against bf16 autocast, alternated
    python benchmarks/bench_train.py --presets cpu --variants fp32,bf16,compile,bf16+compile --batch 32

A variant joins with "+": bf16 (the network under bfloat16 autocast, train.autocast=bf16) and
compile (the network through torch.compile, compiled during the untimed warm-up steps). Each
row's achieved rate is also given against the matmul peak of its own dtype (bf16 rows: a
bfloat16 1024^3 matmul), so a faster number type does not pass for better use of the hardware.

The shipped recipes, as they train: benchmarks/bench_train_recipes.py.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from datagen.scenes import get_shape
from plumbing import config_dir
from datagen.shards import Dataset, Scene
from gns.config import build_config
from gns.data import ObjectTracks, feature_spec
from gns.geometry import quat_from_axis_angle
from gns.graph import MeshLibrary
from gns.checkpoint import build_simulator
from gns.speedups import cpu_line
from gns.train import learning_rate, train_step

CONFIGS = config_dir()
SHAPES = ("beveled_cube", "cylinder", "sphere")  # MOVi-A's shapes: 51-64 vertices each
SYNTHETIC_SPEC = {"floor": {"z": 0.0}, "materials_vary": True}


def synthetic_scenes(shapes=SHAPES, scenes: int = 64, frames: int = 24, seed: int = 0,
                     materials_vary: bool = True) -> list[Scene]:
    """Ballistic spinning tosses; speed depends on graph sizes, not physics."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 12.0
    out = []
    for i in range(scenes):
        p = rng.uniform([-3, -3, 1], [3, 3, 5]) + rng.uniform(-4, 4, 3) * t[:, None] - 5 * t[:, None] ** 2 * [0, 0, 1]
        q = quat_from_axis_angle(rng.normal(size=3), rng.uniform(0, 3) * t)
        zero = np.zeros((frames, 1, 3))
        out.append(Scene(positions=p[:, None], quaternions=q[:, None], velocities=zero, angular_velocities=zero,
                         shape=[shapes[i % len(shapes)]], material=["metal"],
                         scale=np.array([rng.choice([0.7, 1.4]) if materials_vary else 1.0]), mass=np.ones(1),
                         friction=np.array([rng.choice([0.4, 0.8]) if materials_vary else 0.4]),
                         restitution=np.array([rng.choice([0.3, 0.7]) if materials_vary else 0.3])))
    return out


def synthetic_tracks(scenes: int = 64, frames: int = 24, seed: int = 0) -> tuple[ObjectTracks, dict]:
    """Ballistic spinning tosses of the MOVi-A shapes."""
    meshes = {name: (get_shape(name).vertices, get_shape(name).faces) for name in SHAPES}
    return ObjectTracks(synthetic_scenes(SHAPES, scenes, frames, seed), MeshLibrary(meshes)), SYNTHETIC_SPEC


def matmul_gflops(size: int = 1024, seconds: float = 1.0, dtype=torch.float32) -> float:
    a, b = torch.randn(size, size, dtype=dtype), torch.randn(size, size, dtype=dtype)
    for _ in range(3):
        a @ b
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        a @ b
        n += 1
    return 2 * size ** 3 * n / (time.perf_counter() - start) / 1e9


def bench_preset(name: str, tracks: ObjectTracks, spec: dict, steps: int, warmup: int, threads: int | None,
                 autocast: str = "none", compile: bool = False, batch: int | None = None) -> dict:
    overrides = [] if threads is None else [f"train.threads={threads}"]
    if batch is not None:
        overrides.append(f"train.batch_size={batch}")
    cfg = build_config(path=CONFIGS / f"gns_{name}.toml", overrides=overrides)
    threads = cfg.train.threads or os.cpu_count()
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    sim = build_simulator(cfg, spec).train()
    sim.set_speed(autocast, compile)
    optimizer = torch.optim.Adam(sim.parameters(), lr=cfg.train.lr_init)

    def step(i):
        batch = tracks.sample(rng, cfg.train.batch_size, cfg.augment.rotate, cfg.augment.noise_std)
        train_step(sim, optimizer, batch, learning_rate(cfg, i), cfg.train.grad_clip)
        return batch.graph.num_nodes, len(batch.graph.mesh_edges.senders)

    for i in range(warmup):
        step(i)
    flops, nodes, edges = 0, 0, 0
    start = time.perf_counter()
    for i in range(steps):
        n, e = step(warmup + i)
        nodes, edges = nodes + n, edges + e
        flops += 3 * sim.network.forward_flops(n, e)
    elapsed = time.perf_counter() - start
    m = cfg.model
    return {"preset": name + ("+bf16" if autocast == "bf16" else "") + ("+compile" if compile else ""),
            "dtype": "bf16" if autocast == "bf16" else "fp32", "threads": threads, "LxK": f"{m.message_passing_steps}x{m.processor_repeats}", "latent": m.latent_size,
            "batch": cfg.train.batch_size, "nodes": nodes / steps, "edges": edges / steps,
            "steps_per_sec": steps / elapsed, "graphs_per_sec": steps * cfg.train.batch_size / elapsed,
            "gflop_per_step": flops / steps / 1e9, "gflops": flops / elapsed / 1e9}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", help="dataset folder (default: synthetic MOVi-like tosses in memory)")
    p.add_argument("--presets", help="comma list of configs/gns_<name>.toml (default tiny,cpu,paper)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per preset")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps per preset")
    p.add_argument("--threads", type=int, help="torch threads for every preset (default: the preset's)")
    p.add_argument("--autocast", action="store_true",
                   help="time every preset in float32 and under bf16 autocast (train.autocast=bf16), alternated")
    p.add_argument("--variants", help="comma list of fp32, bf16, compile, bf16+compile (default fp32; "
                                      "--autocast = fp32,bf16)")
    p.add_argument("--batch", type=int, help="training batch size for every preset (default: the preset's)")
    p.add_argument("--rounds", type=int, default=1,
                   help="alternate the variants this many times and keep each one's best")
    bench_presets(p.parse_args(argv))


def bench_presets(args) -> None:
    presets = args.presets or "tiny,cpu,paper"
    variants = (args.variants or ("fp32,bf16" if args.autocast else "fp32")).split(",")
    for v in variants:
        for part in v.split("+"):
            if part not in ("fp32", "bf16", "compile"):
                raise SystemExit(f"error: unknown variant {v!r}; parts are fp32, bf16, compile")
    if args.data:
        dataset = Dataset(args.data)
        scenes = dataset.load("train")
        spec = feature_spec(dataset, scenes)
        tracks = ObjectTracks(scenes, MeshLibrary(dataset.meshes))
        source = f"{args.data} ({len(scenes)} train scenes)"
    else:
        tracks = synthetic_tracks()[0]
        spec = SYNTHETIC_SPEC
        source = "synthetic tosses of " + ", ".join(SHAPES)
    print(cpu_line())
    print(f"data: {source}; load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    header = (f"{'preset':<26}{'threads':>8}{'LxK':>6}{'latent':>7}{'batch':>6}{'nodes':>7}{'edges':>7}{'steps/s':>9}"
              f"{'graphs/s':>10}{'GFLOP/step':>11}{'GFLOP/s':>9}{'matmul':>8}{'of peak':>9}")
    print(header)
    print("-" * len(header))
    peaks = {}
    rows = []
    for name in presets.split(","):
        # alternated, so that a change of the machine's load hits all alike
        best = {}
        for _ in range(args.rounds):
            for v in variants:
                parts = set(v.split("+"))
                r = bench_preset(name.strip(), tracks, spec, args.steps, args.warmup, args.threads,
                                 "bf16" if "bf16" in parts else "none", "compile" in parts, args.batch)
                if v not in best or r["steps_per_sec"] > best[v]["steps_per_sec"]:
                    best[v] = r
        rows += [best[v] for v in variants]
    for r in rows:
        key = (r["threads"], r["dtype"])
        if key not in peaks:
            torch.set_num_threads(r["threads"])  # the last preset's count is still set: measure with the row's
            peaks[key] = matmul_gflops(dtype=torch.bfloat16 if r["dtype"] == "bf16" else torch.float32)
        peak = peaks[key]
        print(f"{r['preset']:<26}{r['threads']:>8}{r['LxK']:>6}{r['latent']:>7}{r['batch']:>6}{r['nodes']:>7.0f}"
              f"{r['edges']:>7.0f}{r['steps_per_sec']:>9.2f}{r['graphs_per_sec']:>10.1f}{r['gflop_per_step']:>11.3f}"
              f"{r['gflops']:>9.2f}{peak:>8.1f}{r['gflops'] / peak:>9.1%}")
    print("\nGFLOP counts Linear layers only, training step = 3x forward; matmul = measured 1024^3 "
          "GFLOP/s of the row's dtype (float32, or bfloat16 for bf16 rows) with the same threads.")
    for name in presets.split(","):
        base = next(r for r in rows if r["preset"] == name.strip() or r["preset"].startswith(name.strip() + "+"))
        for r in rows:
            if r is not base and r["preset"].split("+")[0] == name.strip():
                print(f"{r['preset']}: {r['steps_per_sec'] / base['steps_per_sec']:.2f}x the steps/s of {base['preset']}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
