"""How much of a model's one-step error shape matching throws away.

Rollouts keep only the rigid motion of each predicted step (shape matching), while the paper's
loss scores every vertex's acceleration. This splits the one-step acceleration error of a
trained model on training batches (drawn as it was trained: rotation, input noise, contact
share) into its rigid part, the least-squares fit of a rigid field A + alpha x r to each
object's error, and the rest, and prints the rest's share of the squared error: the share of
the loss spent on what no rollout keeps (`train.rigid_loss` scores the kept part; docs/accuracy.md,
session 8). The same split of the target (minus gravity) is printed beside it.

    python -m pipelines.rigid_share --run gns_movi_a_centre --data data/movi_a_4000
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from gns.config import build_config
from gns.checkpoint import load_simulator
from gns.rigid import acceleration_of
from gns.train import load_data
from pipelines.common import guarded


def rigid_projection(field: torch.Tensor, points: torch.Tensor, node_graph: torch.Tensor, num_graphs: int) -> torch.Tensor:
    """The rigid field A + alpha x (r - c) nearest to `field` (N, 3) at `points` (N, 3) per graph, in
    the least-squares sense (c: the graph's vertex mean). Linear: a rigid field is its own
    projection, a field orthogonal to all rigid ones (a swelling r - c) projects to 0."""
    kw = dict(dtype=field.dtype, device=field.device)
    count = torch.zeros(num_graphs, **kw).index_add_(0, node_graph, torch.ones_like(field[:, 0]))[:, None]
    mean = torch.zeros(num_graphs, 3, **kw).index_add_(0, node_graph, field) / count
    r = points - (torch.zeros(num_graphs, 3, **kw).index_add_(0, node_graph, points) / count)[node_graph]
    moment = torch.zeros(num_graphs, 3, **kw).index_add_(0, node_graph, torch.cross(r, field - mean[node_graph], dim=1))
    inertia = torch.zeros(num_graphs, 3, 3, **kw).index_add_(
        0, node_graph, (r * r).sum(1)[:, None, None] * torch.eye(3, **kw) - r[:, :, None] * r[:, None, :])
    alpha = torch.linalg.solve(inertia, moment)
    return mean[node_graph] + torch.cross(alpha[node_graph], r, dim=1)


def _share(values: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]]) -> float:
    kept = lost = 0.0
    for v, x, ng, g in values:
        p = rigid_projection(v, x, ng, g)
        kept += float((p ** 2).sum())
        lost += float(((v - p) ** 2).sum())
    return lost / (kept + lost) if kept + lost > 0 else 0.0


@torch.no_grad()
def rigid_share(run, data, batches: int = 20, batch_size: int = 16, seed: int = 0) -> dict:
    """{"noise_std": {"error_nonrigid_share", "target_nonrigid_share"}} for the training noise and 0."""
    sim, saved = load_simulator(run)   # in eval mode
    cfg = build_config(base=saved["config"])
    spec, tracks, _ = load_data(data, cfg)
    gravity = torch.as_tensor(spec.gravity_per_frame, dtype=torch.float64) if spec.gravity_per_frame is not None \
        else torch.zeros(3, dtype=torch.float64)
    if cfg.train.contact_fraction > 0:
        tracks.mark_contacts(gravity, cfg.train.contact_threshold)
    out = {}
    for noise in sorted({float(cfg.augment.noise_std), 0.0}, reverse=True):
        rng = np.random.default_rng(seed)
        errors, targets = [], []
        for _ in range(batches):
            b = tracks.sample(rng, batch_size, cfg.augment.rotate, noise, contact_fraction=cfg.train.contact_fraction)
            h, g = b.history, b.graph
            predicted = sim.predict_next(h[:, 0], h[:, 1], h[:, 2], g)
            error = predicted - b.target
            target = acceleration_of(h[:, 1], h[:, 2], b.target) - gravity
            errors.append((error, h[:, 2], g.node_graph, g.num_graphs))
            targets.append((target, h[:, 2], g.node_graph, g.num_graphs))
        out[str(noise)] = {"error_nonrigid_share": _share(errors), "target_nonrigid_share": _share(targets)}
    return {"run": str(run), "data": str(data), "batches": batches, "batch_size": batch_size, "by_noise_std": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.rigid_share", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="run folder, checkpoint or shipped model name")
    ap.add_argument("--data", required=True, help="dataset folder (its train split is sampled)")
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--json", help="also write the result here")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    return guarded(lambda: _report(a))


def _report(a) -> None:
    res = rigid_share(a.run, a.data, a.batches, a.batch_size)
    for noise, row in res["by_noise_std"].items():
        print(f"input noise {noise}: {100 * row['error_nonrigid_share']:.1f}% of the one-step squared error is "
              f"non-rigid (thrown away by shape matching); target: {100 * row['target_nonrigid_share']:.1f}%")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
