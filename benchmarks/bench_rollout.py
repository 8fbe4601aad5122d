"""Rollout speed of the GNS, before and after each saving, measured in the same run.

Rolls out MOVi-A-like single-object tracks (beveled cube, cylinder, sphere; 51-64 vertices)
with an untrained model of a preset (a forward pass costs the same whatever the weights) and
prints, per variant: ms per rollout step, ms of wall clock per simulated second per
trajectory, the speed-up over the "before" row of its group, and the largest difference of
the trajectories from the current code's (0 or float32 rounding: a saving must not change
results). Then where the time of one step goes, so the savings not taken are sized too.

    python benchmarks/bench_rollout.py                 # cpu preset, 40 tracks, 21 steps
    python benchmarks/bench_rollout.py --preset paper --tracks 8
"""
from __future__ import annotations

import argparse
import cProfile
import importlib.util
import os
import pstats
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import gns.network
from gns.config import build_config
from gns.evaluate import rollout_tracks
from gns.checkpoint import build_simulator

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("bench_train", HERE / "bench_train.py")
bench_train = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_train)


def concatenated_edge_messages(module, nodes, edges, senders, receivers, per_node: bool = True):
    """The textbook first edge layer: [E, V_r, V_s] gathered per edge, then one Linear (O(E)),
    for every edge set (`per_node`, which part of gns.network._edge_messages applies, is moot)."""
    w = torch.cat([module.edge_in.weight, module.receiver_in.weight, module.sender_in.weight], dim=1)
    x = torch.cat([edges, nodes[receivers], nodes[senders]], dim=1)
    return module.edge_rest(F.linear(x, w, module.edge_in.bias))


@contextmanager
def edge_messages(fn):
    saved = gns.network._edge_messages
    gns.network._edge_messages = fn
    try:
        yield
    finally:
        gns.network._edge_messages = saved


def timed(sim, tracks, which: torch.Tensor, frames: int, batch: int, repeats: int) -> tuple[float, torch.Tensor]:
    """Best-of-`repeats` seconds to roll out `which` in calls of `batch` tracks; and the positions."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        parts = [rollout_tracks(sim, tracks, which[k:k + batch], frames)[0] for k in range(0, len(which), batch)]
        best = min(best, time.perf_counter() - t0)
        out = torch.from_numpy(np.concatenate(parts, axis=1))
    return best, out


def breakdown(sim, tracks, which, frames) -> list[tuple[str, float]]:
    """Share of one rollout's time in the network, the features, shape matching and the rest."""
    prof = cProfile.Profile()
    prof.runcall(rollout_tracks, sim, tracks, which, frames)
    stats = pstats.Stats(prof).stats
    total = max(v[3] for v in stats.values())

    def cumulative(name_part: str, func: str) -> float:
        return sum(v[3] for (f, _, fn), v in stats.items() if name_part in f and fn == func)
    # the outermost forward of gns/network.py (EncodeProcessDecode) holds the blocks' forwards
    network = max(v[3] for (f, _, fn), v in stats.items() if f.endswith("gns/network.py") and fn == "forward")
    parts = [("network (encode, process, decode)", network),
             ("node and edge features + normalisers", cumulative("gns/simulator.py", "_inputs")),
             ("shape matching (rollout and poses)", cumulative("gns/geometry.py", "shape_match_packed"))]
    parts.append(("everything else (integration, bookkeeping)", total - sum(p for _, p in parts)))
    return [(name, p / total) for name, p in parts]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="cpu", help="configs/gns_<name>.toml (default cpu)")
    ap.add_argument("--tracks", type=int, default=40, help="tracks rolled out (default 40)")
    ap.add_argument("--frames", type=int, default=24, help="frames per track incl. the 3 given (default 24)")
    ap.add_argument("--repeats", type=int, default=3, help="timings per variant; the best is kept (default 3)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    tracks, spec = bench_train.synthetic_tracks(a.tracks, frames=a.frames)
    cfg = build_config(path=bench_train.CONFIGS / f"gns_{a.preset}.toml")
    torch.manual_seed(0)
    sim = build_simulator(cfg, spec).eval()
    which = torch.arange(a.tracks)
    steps = a.tracks * (a.frames - 3)
    simulated = steps / 12.0
    print(f"preset {a.preset}, {a.tracks} tracks x {a.frames - 3} steps, {a.threads} thread(s); "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    _, reference = timed(sim, tracks, which, a.frames, a.tracks, 1)
    rows = []
    with edge_messages(concatenated_edge_messages):
        rows.append(("first edge layer", "before: concatenated [E, V_r, V_s], O(E)", *timed(sim, tracks, which, a.frames, a.tracks, a.repeats)))
    rows.append(("first edge layer", "now: node parts once per node, O(N)", *timed(sim, tracks, which, a.frames, a.tracks, a.repeats)))
    rows.append(("batching", "before: one track per call", *timed(sim, tracks, which, a.frames, 1, 1)))
    rows.append(("batching", f"now: {a.tracks} tracks per call", *timed(sim, tracks, which, a.frames, a.tracks, a.repeats)))
    header = f"{'saving':<18}{'variant':<46}{'ms/step':>9}{'ms/sim-s/traj':>15}{'speed-up':>10}{'max diff':>10}"
    print(header)
    print("-" * len(header))
    before = {}
    for group, label, seconds, pos in rows:
        before.setdefault(group, seconds)
        diff = float((pos - reference).abs().max())
        print(f"{group:<18}{label:<46}{seconds / (a.frames - 3) * 1e3:>9.2f}{seconds / simulated * 1e3:>15.2f}"
              f"{before[group] / seconds:>9.2f}x{diff:>10.1e}")
    print("\nwhere one batched rollout's time goes:")
    for name, share in breakdown(sim, tracks, which, a.frames):
        print(f"  {name:<46}{share:>7.1%}")


if __name__ == "__main__":
    main()
