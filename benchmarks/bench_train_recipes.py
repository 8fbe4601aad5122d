"""Training speed of the shipped recipes, as they train, against the matmul rate at their own shapes.

Recipes (configs/recipes/<name>.toml, `--recipe`): the first run of the recipe, or the one named
after a colon (movi_a:pushforward), set up and stepped with gns.train's own helpers: its model
preset and settings (batch size, features and node selection, contact windows, pushforward steps,
rigid loss, weight average, autocast with "auto" resolved here, compile, threads), from
train.init_from's weights where they are found here (movi_a_multi: the shipped movi_a), else from
fresh ones. A timed step is the training loop's: draw the batch, one Adam step, the weight average's.

    python benchmarks/bench_train_recipes.py --recipe movi_a,movi_a:pushforward,movi_a_multi --rounds 2
    python benchmarks/bench_train_recipes.py --recipe real_cubes --src data/contactnets --shapes

- GFLOP/step: every 2-D matrix product (aten mm and addmm) the step runs, forward and backward
  (2 per multiply-add), on an eager replay of a timed step of each distinct set of graph sizes:
  the graph the network sees (after node selection, with its collision edges) and the products
  autograd runs (none for frozen weights or for the input layers' gradients for the data).
- matmul at the batch's shapes ("shapes"): the first round's median step's products (by FLOPs),
  each distinct one (op, shapes, strides, dtype) timed alone on random operands of that layout
  (best of 5 runs of at least 10 ms, best over the rounds), with the same threads. The fraction,
  achieved / that rate, is the share of the step's time its products would take on their own:
  100% is a step that is nothing but its matrix products, each as fast as it runs alone.
- 1024^3: the same threads' rate for a 1024 x 1024 product in the recipe's dtype, for scale.

Data: a datagen recipe's first --scenes training scenes as the recipe makes them (cached in --cache);
a ContactNets recipe's real tosses from --src. Without --src, or with --synthetic, ballistic tosses
of the recipe's shapes, one object a scene (the row's data column says which).
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path[:0] = [str(Path(__file__).resolve().parent.parent), str(Path(__file__).resolve().parent)]

from bench_train import CONFIGS, SHAPES, matmul_gflops, synthetic_scenes  # noqa: E402
from datagen.scenes import get_shape  # noqa: E402
from gns.config import build_config  # noqa: E402
from gns.data import ObjectTracks  # noqa: E402
from gns.graph import MeshLibrary, graph_settings  # noqa: E402
from gns.run_folder import World  # noqa: E402
from gns.speedups import cpu_line  # noqa: E402
from gns.train import learning_rate, train_step, unrolled_loss  # noqa: E402


PRODUCTS = (torch.ops.aten.mm.default, torch.ops.aten.addmm.default)


class Product(NamedTuple):
    """One matrix product as the step ran it: the op and its arguments (tensors by shape, strides
    and dtype), enough to run it again alone."""
    # a NamedTuple, not a dataclass: the tests load this file without registering it as a module
    op: object
    args: tuple
    kwargs: tuple

    @property
    def flops(self) -> int:
        a, b = self.args[-2:]
        return 2 * a[0][0] * a[0][1] * b[0][1]

    def operands(self) -> tuple[list, dict]:
        def make(meta):
            if not (isinstance(meta, tuple) and len(meta) == 3 and isinstance(meta[2], torch.dtype)):
                return meta
            shape, stride, dtype = meta
            size = 1 + sum((n - 1) * s for n, s in zip(shape, stride)) if all(shape) else 0
            return torch.randn(size, dtype=torch.float32).to(dtype).as_strided(shape, stride)
        return [make(a) for a in self.args], dict(self.kwargs)

    def seconds(self, rounds: int = 5, least: float = 0.01) -> float:
        """Best of `rounds` of the mean time of one call, each round at least `least` seconds."""
        args, kwargs = self.operands()
        self.op(*args, **kwargs)

        def mean(calls: int) -> float:
            start = time.perf_counter()
            for _ in range(calls):
                self.op(*args, **kwargs)
            return (time.perf_counter() - start) / calls
        calls = 1
        while (took := mean(calls)) * calls < least:
            calls *= 2
        return min([took] + [mean(calls) for _ in range(rounds - 1)])

    def label(self) -> str:
        a, b = self.args[-2:]
        transposed = lambda m: "T" if len(m[1]) == 2 and m[1][0] == 1 and m[0][1] > 1 else ""  # noqa: E731
        return (f"{self.op.__name__.split('.')[0]} ({a[0][0]}x{a[0][1]}){transposed(a)} "
                f"({b[0][0]}x{b[0][1]}){transposed(b)} {str(a[2]).removeprefix('torch.')}")


def _meta(a):
    return (tuple(a.shape), tuple(a.stride()), a.dtype) if isinstance(a, torch.Tensor) else a


class RecordProducts(TorchDispatchMode):
    """Every 2-D matrix product run inside, forward and backward (autograd's own products are
    dispatched here too), as Products."""

    def __init__(self):
        super().__init__()
        self.products: list[Product] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in PRODUCTS:
            self.products.append(Product(func, tuple(_meta(a) for a in args),
                                         tuple(sorted((k, _meta(v)) for k, v in kwargs.items()))))
        return func(*args, **kwargs)


def recipe_config(recipe, run, threads: int | None, batch: int | None):
    """The config of the recipe's run `run` and a note on what differs from it. Its
    train.init_from is kept where it names weights found here (movi_a_multi grows onto the
    shipped movi_a, and train.collisions_only freezes those weights and their normalisers), else
    left out with collisions_only: fresh weights train at the same speed."""
    from gns.checkpoint import CheckpointError, checkpoint_of
    from pipelines.recipe import run_overrides
    overrides, note = list(run_overrides(run, None)), ""
    start = next((o.split("=", 1)[1].strip('"') for o in overrides if o.startswith("train.init_from=")), None)
    if start is not None:
        try:
            found = checkpoint_of(start).is_file()
        except (CheckpointError, OSError):   # a name outside the zoo, an unreadable path
            found = False
        if found:
            note = f"; from {start}'s weights (train.init_from)"
        else:
            overrides = [o for o in overrides if not o.startswith(("train.init_from=", "train.collisions_only="))]
            note = f"; from fresh weights, all training ({start}, its train.init_from, is not here)"
    if threads is not None:
        overrides.append(f"train.threads={threads}")
    if batch is not None:
        overrides.append(f"train.batch_size={batch}")
    return build_config(path=CONFIGS / f"{recipe.model}.toml", overrides=overrides), note


def recipe_data(recipe, cfg, scenes: int, src: Path | None, cache: Path, synthetic: bool):
    """(feature spec, train tracks, data tag for the row, a sentence on the data) for the recipe's
    run: its own data where it can be made here, else synthetic tosses of its shapes."""
    from gns.data import load_data
    from pipelines.common import data_stage
    from pipelines.recipe import data_stage_of, scene_sets
    d = recipe.data
    kind = d.get("kind", "datagen")
    real = kind.startswith("contactnets")
    ds = None
    if not synthetic and kind == "datagen":
        n = min(scenes, int(d.get("train", scenes)))
        seed = int(d.get("seed", 0))
        ds = data_stage(cache / f"{recipe.name}_seed{seed}_{n}", scene_sets(d), {"train": n}, seed, workers=1)
        tag = f"datagen {n}"
        about = f"the first {n} of its {d.get('train', '?')} training scenes (datagen, seed {seed})"
    elif not synthetic and kind == "tilted_drops":
        from pipelines.diagnostic_45 import training_data_stage
        n = min(scenes, int(d["train"]))
        ds = training_data_stage(cache / f"{recipe.name}_{n}", {"train": n}, int(d["seed"]),
                                 shapes=d.get("shapes", ("cube",)), max_heights=d.get("max_heights", (0.05,)))
        tag, about = f"drops {n}", f"{n} of its {d['train']} training drops"
    elif not synthetic and real and src is not None:
        ds, _ = data_stage_of(replace(recipe, data={**d, "kind": "contactnets"}), cache / recipe.name, None, src, 1)
        only = " (only the real ones: its MuJoCo tosses are not made)" if kind == "contactnets_mujoco" else ""
        tag, about = f"real {d['tosses']}", f"its {d['tosses']} real ContactNets training tosses{only}"
    if ds is not None:
        spec, tracks, _ = load_data(ds.root, cfg)
        return spec, tracks, tag, about
    shapes = d.get("scene", {}).get("shapes") or d.get("shapes") or (["cube"] if real else SHAPES)
    vary = not real   # one material in the real tosses
    meshes = {s: (get_shape(s).vertices, get_shape(s).faces) for s in shapes}
    library = MeshLibrary(meshes, **graph_settings(cfg.features))
    tracks = ObjectTracks(synthetic_scenes(tuple(shapes), 64, 24, 0, vary), library, unroll=cfg.train.unroll_steps)
    why = "--synthetic" if synthetic else ("no --src" if real else f"data kind {kind}")
    from gns.spec import ModelSpec
    spec = ModelSpec.from_dict({"floor": {"z": 0.0}, "materials_vary": vary}, partial=True)
    return (spec, tracks, "synthetic",
            f"synthetic ballistic tosses of {', '.join(shapes)}, one object a scene ({why}): not the recipe's data")


class RecipeRun:
    """A recipe's run (`recipe` or `recipe:run`; its first run by default) set up as gns.train sets it
    up (gns.train's own helpers), ready to step."""

    def __init__(self, name: str, threads: int | None, batch: int | None, scenes: int, src: Path | None,
                 cache: Path, synthetic: bool):
        from gns.train import _build_model, _place_model
        from pipelines.recipe import load_recipe
        self.name = name
        name, _, stage = name.partition(":")
        self.recipe = load_recipe(name)
        runs = [r for r in self.recipe.runs if r.name == stage] if stage else self.recipe.runs
        if not runs:
            raise SystemExit(f"error: recipe {name} has no run {stage!r} ({', '.join(r.name for r in self.recipe.runs)})")
        cfg, note = recipe_config(self.recipe, runs[0], threads, batch)
        self.cfg = cfg
        self.threads = cfg.train.threads or os.cpu_count()
        self.spec, self.tracks, self.tag, self.source = recipe_data(self.recipe, cfg, scenes, src, cache, synthetic)
        self.source += note
        torch.set_num_threads(self.threads)
        torch.manual_seed(cfg.train.seed)
        self.rng = np.random.default_rng(cfg.train.seed)
        self.world = World()
        self.sim, self.optimizer, _, self.step_count, self.average = _build_model(cfg, self.spec, None, self.rng)
        _place_model(self.sim, cfg, torch.device("cpu"), self.world, cfg.train.steps)
        self.dtype = "bf16" if self.sim.autocast_used == "bf16" else "fp32"
        self.calls: list[tuple[int, int, int, bool]] = []   # nodes, edges, collision edges, grad
        network = self.sim.run_network

        def counted(*args):
            self.calls.append((args[0].shape[0], args[1].shape[0], args[4].shape[0] if len(args) > 4 else 0,
                               torch.is_grad_enabled()))
            return network(*args)
        # the sizes of the graph the network is handed, after node selection and collision edges
        self.sim.run_network = counted

    def step(self):
        """One step of gns.train's loop; returns (its batch, seconds drawing it)."""
        from gns.train import _next_batch
        cfg = self.cfg
        lr = learning_rate(cfg, self.step_count)
        start = time.perf_counter()
        batch, fraction = _next_batch(self.tracks, self.rng, cfg, self.world)
        drawn = time.perf_counter() - start
        batch = batch.to("cpu")
        train_step(self.sim, self.optimizer, batch, lr, cfg.train.grad_clip, fraction, 1, cfg.train.rigid_loss)
        if self.average is not None:
            self.average.update()
        self.step_count += 1
        return batch, drawn

    def timed(self, steps: int) -> dict:
        """`steps` steps timed together, with each step's batch and the sizes of its network calls."""
        batches, calls, drawing = [], [], 0.0
        # torch's thread count is process-wide, and recipes of other counts step in between
        torch.set_num_threads(self.threads)
        start = time.perf_counter()
        for _ in range(steps):
            before = len(self.calls)
            batch, drawn = self.step()
            batches.append(batch)
            calls.append(tuple(self.calls[before:]))
            drawing += drawn
        elapsed = time.perf_counter() - start
        self.calls.clear()
        return {"elapsed": elapsed, "steps": steps, "batches": batches, "calls": calls, "drawing": drawing}

    def products(self, batch) -> list[Product]:
        """The matrix products of one training step on `batch`, replayed eagerly (a compiled
        network's products are the same ones, inside its code); the weights do not change, the
        normalisers take the batch in as a training step does."""
        self.sim.set_speed(self.sim.autocast_used, False)
        with RecordProducts() as record:
            unrolled_loss(self.sim, batch, self.cfg.train.rigid_loss).backward()
        self.optimizer.zero_grad(set_to_none=True)
        self.sim.set_speed(self.sim.autocast_used, self.cfg.train.compile)
        return record.products


class Reference:
    """The matrix products of one step, each timed alone (Product.seconds), best over the rounds."""

    def __init__(self, products: list[Product]):
        self.counts = Counter(products)
        self.flops = sum(p.flops for p in products)
        self.best = {p: math.inf for p in self.counts}

    def time(self) -> None:
        for p in self.counts:
            self.best[p] = min(self.best[p], p.seconds())

    @property
    def seconds(self) -> float:
        return sum(n * self.best[p] for p, n in self.counts.items())

    def show(self, name: str) -> None:
        total = self.seconds
        print(f"\n{name}: the median step's {sum(self.counts.values())} products, each timed alone "
              f"({self.flops / 1e9:.3f} GFLOP in {total * 1e3:.2f} ms)")
        for p, n in sorted(self.counts.items(), key=lambda kv: -kv[1] * self.best[kv[0]]):
            print(f"  {n:>4} x {p.label():<44} {p.flops / self.best[p] / 1e9:>8.1f} GFLOP/s "
                  f"{n * self.best[p] / total:>6.1%} of the time")


def bench_recipes(names: list[str], args) -> list[dict]:
    """The recipes stepped in alternation for args.rounds rounds, each round followed by the
    reference products' timing; a row per recipe from its fastest round."""
    cache = Path(args.cache) if args.cache else Path(tempfile.gettempdir()) / "bench_train_data"
    src = Path(args.src) if args.src else None
    runs = [RecipeRun(n, args.threads, args.batch, args.scenes, src, cache, args.synthetic) for n in names]
    for run in runs:
        # compiling happens here, in the first steps, untimed
        warm = run.timed(args.warmup)["elapsed"]
        print(f"{run.name}: warm-up {args.warmup} steps in {warm:.1f} s", flush=True)
    timings: list[list[dict]] = [[] for _ in runs]
    references: list[Reference] = []
    for _ in range(args.rounds):
        # alternated, so that a change of the machine's load hits all alike
        for run, rounds in zip(runs, timings):
            rounds.append(run.timed(args.steps))
        for i, (run, rounds) in enumerate(zip(runs, timings)):
            if i == len(references):
                first = rounds[0]
                work = [sum(run.sim.network.forward_flops(n, e, c) for n, e, c, _ in calls) for calls in first["calls"]]
                references.append(Reference(run.products(first["batches"][work.index(statistics.median_low(work))])))
            torch.set_num_threads(run.threads)
            references[i].time()
    if args.shapes:
        for run, ref in zip(runs, references):
            ref.show(f"{run.name}, {run.threads} thread{'s' if run.threads > 1 else ''}")
    peaks: dict = {}
    rows = []
    for run, rounds, ref in zip(runs, timings, references):
        best = max(rounds, key=lambda t: t["steps"] / t["elapsed"])
        # one replay per distinct set of network calls: the products are those of the graph sizes
        # alone, the same for any batch of those sizes
        replayed: dict[tuple, int] = {}
        for batch, calls in zip(best["batches"], best["calls"]):
            if calls not in replayed:
                replayed[calls] = sum(p.flops for p in run.products(batch))
        flops = sum(replayed[calls] for calls in best["calls"])
        key = (run.threads, run.dtype)
        if key not in peaks:
            torch.set_num_threads(run.threads)
            peaks[key] = matmul_gflops(dtype=torch.bfloat16 if run.dtype == "bf16" else torch.float32)
        calls = [c for step in best["calls"] for c in step]
        nodes, edges, collisions = (sum(c[k] for c in calls) / len(calls) for k in range(3))
        steps, elapsed = best["steps"], best["elapsed"]
        rows.append({"recipe": run.name, "dtype": run.dtype + ("+compile" if run.cfg.train.compile else ""),
                     "threads": run.threads, "batch": run.cfg.train.batch_size, "nodes": nodes, "edges": edges,
                     "collisions": collisions, "steps_per_sec": steps / elapsed,
                     "drawing": best["drawing"] / elapsed, "gflop_per_step": flops / steps / 1e9,
                     "gflops": flops / elapsed / 1e9, "at_shapes": ref.flops / ref.seconds / 1e9,
                     "peak": peaks[key], "data": run.tag, "source": run.source})
    return rows


def print_recipes(rows: list[dict]) -> None:
    w = max(14, *(len(r["recipe"]) + 1 for r in rows))
    header = (f"{'recipe':<{w}}{'dtype':>13}{'threads':>8}{'batch':>6}{'nodes':>7}{'edges':>7}{'coll.':>6}"
              f"{'steps/s':>9}{'batch%':>7}{'GFLOP/step':>11}{'GFLOP/s':>9}{'shapes':>8}{'of them':>8}"
              f"{'1024^3':>8}{'of it':>7}  data")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['recipe']:<{w}}{r['dtype']:>13}{r['threads']:>8}{r['batch']:>6}{r['nodes']:>7.0f}{r['edges']:>7.0f}"
              f"{r['collisions']:>6.0f}{r['steps_per_sec']:>9.2f}{r['drawing']:>7.1%}{r['gflop_per_step']:>11.4f}"
              f"{r['gflops']:>9.2f}{r['at_shapes']:>8.1f}{r['gflops'] / r['at_shapes']:>8.1%}"
              f"{r['peak']:>8.1f}{r['gflops'] / r['peak']:>7.1%}  {r['data']}")
    print("\nnodes, edges, coll.: the graph the network is handed (after node selection; mesh and collision edges), "
          "a mean over its calls; batch%: the share of the step spent drawing the batch; GFLOP/step: the step's 2-D "
          "matrix products, forward and backward, replayed; shapes: GFLOP/s of the median step's products each timed "
          "alone in the row's dtype, best over the rounds (see the docstring), 'of them' the achieved rate's share of "
          "it; 1024^3: a 1024^3 product in the row's dtype, same threads. Each row is its recipe's fastest round.")
    for r in rows:
        print(f"{r['recipe']}: {r['source']}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--recipe", action="append", default=[],
                   help="a recipe of configs/recipes, or RECIPE:RUN (repeatable or a comma list): time its first "
                        "run, or the one named, as it trains")
    p.add_argument("--steps", type=int, default=20, help="timed steps per recipe and round")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps per recipe")
    p.add_argument("--threads", type=int, help="torch threads for every recipe (default: its own)")
    p.add_argument("--batch", type=int, help="training batch size for every recipe (default: its own)")
    p.add_argument("--rounds", type=int, default=1, help="alternate the recipes this many times and keep each one's best")
    p.add_argument("--scenes", type=int, default=64, help="recipes: training scenes to generate (default 64)")
    p.add_argument("--src", help="recipes on ContactNets tosses: the folder holding tosses_processed/")
    p.add_argument("--cache", help="recipes: where generated and imported data are kept (default: a folder "
                                   "in the system's temporary directory)")
    p.add_argument("--synthetic", action="store_true", help="recipes: synthetic tosses of their shapes, not their data")
    p.add_argument("--shapes", action="store_true", help="recipes: list each one's matrix products and their rates")
    args = p.parse_args(argv)

    recipes = [n.strip() for arg in args.recipe for n in arg.split(",") if n.strip()]
    print(cpu_line())
    if recipes:
        print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores\n", flush=True)
        rows = bench_recipes(recipes, args)
        print()
        print_recipes(rows)
        print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
