"""One-step errors: each step predicted from the true history, split by contact.

A rollout's error compounds; this asks what a single step gets wrong before anything compounds.
Every frame t of every track is predicted from the true frames t-2, t-1, t (teacher forcing),
shape-matched, and compared with the true frame t+1: the centre's error in % of the object's
size and the rotation error in degrees. A step is "in contact" when the true centre
acceleration differs from gravity by more than half of it (the threshold of
`train.contact_threshold`), else "airborne". The share of the error in contact steps says where
a model's rollout error is made; an airborne step is what free flight (`--free-flight`) makes
exact far from the floor.

    python -m pipelines.one_step --run movi_a --data data/movi_a_4000 --limit 100 --symmetrize
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from gns.config import TrainConfig
from gns.data import ObjectTracks, in_contact
from gns.checkpoint import load_simulator
from gns.evaluate import load_split
from gns.spec import RolloutOptions
from gns.geometry import matrix_to_quat
from gns.metrics import object_width, rotation_error_deg
from gns.geometry import shape_match_packed
from gns.spec import ModelSpec

CONTACT = TrainConfig.contact_threshold  # |a - g| > CONTACT |g|: the step is in contact (gns.data.in_contact)


def one_step_errors(run, data, split: str = "test", limit: int | None = None, symmetrize: bool = False,
                    autocast: str = "none") -> dict:
    """{"contact": {...}, "airborne": {...}, "contact_share_of_rotation_error": float, "by_shape":
    {shape: {"contact": {...}, "airborne": {...}}}} where each part holds the mean position error (% of size) and rotation error (degrees) of one step,
    the 50/90/99th percentiles of the rotation error and the number of steps."""
    sim, saved = load_simulator(run, options=RolloutOptions(symmetrize=symmetrize, autocast=autocast))
    sim.eval()
    spec = ModelSpec.from_dict(saved["spec"])
    ds, scenes = load_split(data, split, limit, spec.frame_rate)
    tracks = ObjectTracks(scenes, sim.mesh_library(ds.meshes), name=f"{split} split")
    frames = int(tracks.length.min())
    which = torch.arange(tracks.num_tracks)
    graph, verts, centres = tracks.track_vertices(which, frames)
    _, true_rot = tracks.poses(which, torch.zeros_like(which), frames)
    g = torch.as_tensor(ds.gravity, dtype=torch.float64) / ds.frame_rate ** 2
    contact = in_contact(centres, g, CONTACT)[:, 2:frames - 1].T.numpy()   # (steps, tracks): frame t -> t+1
    rot, pos, turned, true_turn = [], [], [], []
    with torch.no_grad():
        for t in range(2, frames - 1):
            x = sim.predict_next(verts[:, t - 2], verts[:, t - 1], verts[:, t], graph)
            r_pred, c_pred, _ = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
            q_now, q_pred = matrix_to_quat(true_rot[:, t].numpy()), matrix_to_quat(r_pred.numpy())
            q_next = matrix_to_quat(true_rot[:, t + 1].numpy())
            rot.append(rotation_error_deg(q_pred, q_next))
            pos.append((c_pred - centres[:, t + 1]).norm(dim=-1).numpy())
            turned.append(rotation_error_deg(q_now, q_pred))     # the angle the step turned the object
            true_turn.append(rotation_error_deg(q_now, q_next))
    rot, pos, turned, true_turn = np.array(rot), np.array(pos), np.array(turned), np.array(true_turn)
    width = np.asarray([object_width(float(sc.scale[n]), np.asarray(ds.meshes[sc.shape[n]][0]))
                        for sc in scenes for n in range(sc.num_objects)])  # tracks are numbered scene by scene
    pos = 100.0 * pos / width[None, :]

    def stats(mask: np.ndarray) -> dict:
        return {"steps": int(mask.sum()),
                "position_error_pct": float(pos[mask].mean()) if mask.any() else None,
                "rotation_error_deg": float(rot[mask].mean()) if mask.any() else None,
                "rotation_percentiles_50_90_99": np.percentile(rot[mask], [50, 90, 99]).tolist()
                if mask.any() else None,
                # the angle turned in one step, predicted over true (summed): below 1, the
                # model turns objects too little from the true history, a bias a rollout adds up
                "spin_ratio": float(turned[mask].sum() / max(true_turn[mask].sum(), 1e-300)) if mask.any() else None}
    out = {"contact": stats(contact), "airborne": stats(~contact)}
    out["contact_share_of_rotation_error"] = float(rot[contact].sum() / max(rot.sum(), 1e-300))
    # per shape: whether a shape's rollout error starts in its contact steps or in flight
    shape = np.asarray([sc.shape[n] for sc in scenes for n in range(sc.num_objects)])[None, :]
    out["by_shape"] = {str(name): {"contact": stats(contact & (shape == name)), "airborne": stats(~contact & (shape == name))}
                       for name in np.unique(shape)}
    out.update(run=str(run), data=str(data), split=split, num_tracks=int(tracks.num_tracks),
               frames_per_track=frames, symmetrize=symmetrize, autocast=autocast)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.one_step", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="run folder, checkpoint or shipped model name")
    ap.add_argument("--data", required=True, help="dataset folder")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, help="first N scenes only")
    ap.add_argument("--symmetrize", action="store_true", help="average each step over the floor's mirror images")
    ap.add_argument("--autocast", choices=["none", "bf16", "auto"], default="none")
    ap.add_argument("--json", help="also write the result here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    res = one_step_errors(args.run, args.data, args.split, args.limit, args.symmetrize, args.autocast)
    for name in ("contact", "airborne"):
        r = res[name]
        if r["steps"]:
            p50, p90, p99 = r["rotation_percentiles_50_90_99"]
            print(f"{name:8s} {r['steps']:6d} steps: position {r['position_error_pct']:.3g}% of size, rotation "
                  f"{r['rotation_error_deg']:.3g} deg (50/90/99%: {p50:.3g} / {p90:.3g} / {p99:.3g}), "
                  f"spin ratio {r['spin_ratio']:.3f}")
    print(f"contact steps hold {100 * res['contact_share_of_rotation_error']:.0f}% of the one-step rotation error")
    print("per shape, position % / rotation deg:      contact        airborne")
    for name, parts in res["by_shape"].items():
        cells = [f"{r['position_error_pct']:6.3g} / {r['rotation_error_deg']:<6.3g}" if r["steps"] else "       -       "
                 for r in (parts["contact"], parts["airborne"])]
        print(f"  {name:38s} {cells[0]}  {cells[1]}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
