"""One-step errors: each step predicted from the true history, split by contact.

A rollout's error compounds; this asks what a single step gets wrong before anything compounds.
Every frame t of every track is predicted from the true frames t-2, t-1, t (teacher forcing),
shape-matched, and compared with the true frame t+1: the centre's error in % of the object's
size and the rotation error in degrees. A step is "in contact" when the true centre
acceleration differs from gravity by more than half of it (the threshold of
`train.contact_threshold`), else "airborne". The share of the error in contact steps says where
a model's rollout error is made; an airborne step is what free flight (`--free-flight`) makes
exact far from the floor. A model with collision edges also gets the steps on which an object
has one ("objects near", a subset of both).

`--physics` sets a floor under these errors: PyBullet, as the dataset was made, stepped one frame
from each pose with the velocities of the last two frames' finite differences. It is exact from
the true state, so what it gets wrong is what the history does not tell (an impact between two
frames, the spin an object had) and a model could not know either; a model far above it on some
steps has that much left to learn there. Needs a dataset made by `datagen toss`.

    python -m pipelines.one_step --run movi_a --data data/movi_a_4000 --limit 100 --symmetrize
    python -m pipelines.one_step --run movi_a_multi --data data/multi_test --limit 40 --autocast auto --physics
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from gns.config import TrainConfig
from pipelines.common import guarded
from plumbing import DataError
from gns.data import ObjectTracks, in_contact
from gns.checkpoint import load_simulator
from gns.evaluate import load_split
from gns.spec import RolloutOptions
from gns.geometry import matrix_to_quat
from gns.metrics import object_width, rotation_error_deg
from gns.geometry import shape_match_packed
from gns.spec import ModelSpec

CONTACT = TrainConfig.contact_threshold  # |a - g| > CONTACT |g|: the step is in contact (gns.data.in_contact)


def toss_settings(ds) -> tuple[dict, int, float, int]:
    """The config, seed, frame rate and physics steps a frame of a `datagen toss` dataset, or the
    DataError that --physics cannot run on it (checked before the model pass, so it comes first)."""
    if ds.meta.get("generator") != "datagen toss" or "config" not in ds.meta:
        raise DataError(f"{ds.root}: --physics needs a dataset made by `datagen toss` (its config rebuilds the scenes)")
    cfg, rate = ds.meta["config"], float(ds.frame_rate)
    sub = round(float(cfg["physics"]["rate"]) / rate)
    if abs(sub * rate - float(cfg["physics"]["rate"])) > 1e-9:
        raise DataError(f"{ds.root}: read at {rate} fps, which does not divide its physics rate {cfg['physics']['rate']} Hz")
    return cfg, int(ds.meta["seed"]), rate, sub


def physics_from_history(ds, scenes: list, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """PyBullet as `datagen toss` made the dataset, one frame from each frame t in 2 .. frames-2
    of every scene, started from the recorded poses at t with velocities from frames t-1 and t:
    (steps, tracks) distances to the true centre at t+1 (scene units) and rotation errors
    (degrees), tracks numbered scene by scene as gns.data.ObjectTracks numbers them."""
    import pybullet as pb
    from dataclasses import replace
    from scipy.spatial.transform import Rotation
    from datagen.scenes import sample_scene
    from datagen.shards import wxyz, xyzw
    from datagen.toss import build_world
    cfg, seed, rate, sub = toss_settings(ds)
    lag = np.asarray(cfg["physics"]["gravity"], float) * (1 - 1 / sub) / (2 * rate)
    pos_err, rot_err, client = [], [], pb.connect(pb.DIRECT)
    try:
        for sc in scenes:
            split, _, index = str(sc.attrs["scene_id"]).partition("-")
            spec = sample_scene(cfg, seed, split, int(index))
            if len(spec.objects) != sc.num_objects or not np.allclose(
                    [o.position for o in spec.objects], sc.positions[0], atol=1e-9 * (1 + np.abs(sc.positions[0]).max())):
                raise DataError(f"{ds.root}: scene {sc.attrs['scene_id']} is not what its config and seed give")
            p_s, r_s = np.zeros((frames - 3, sc.num_objects)), np.zeros((frames - 3, sc.num_objects))
            for t in range(2, frames - 1):
                turn = Rotation.from_quat(xyzw(sc.quaternions[t])) * Rotation.from_quat(xyzw(sc.quaternions[t - 1])).inv()
                # the mean velocity over the last frame, advanced by gravity to its end: exact in flight
                # under the engine's symplectic Euler steps of 1 / (sub x rate)
                objects = [replace(o, position=sc.positions[t, j], quaternion=sc.quaternions[t, j],
                                   velocity=(sc.positions[t, j] - sc.positions[t - 1, j]) * rate + lag,
                                   angular_velocity=turn[j].as_rotvec() * rate) for j, o in enumerate(spec.objects)]
                c, bodies = build_world(replace(spec, objects=objects), cfg, client)
                for _ in range(sub):
                    pb.stepSimulation(physicsClientId=c)
                poses = [pb.getBasePositionAndOrientation(b, physicsClientId=c) for b in bodies]
                p_s[t - 2] = np.linalg.norm(np.array([p for p, _ in poses]) - sc.positions[t + 1], axis=-1)
                r_s[t - 2] = rotation_error_deg(np.array([wxyz(q) for _, q in poses]), sc.quaternions[t + 1])
            pos_err.append(p_s)
            rot_err.append(r_s)
    finally:
        pb.disconnect(client)
    return np.concatenate(pos_err, axis=1), np.concatenate(rot_err, axis=1)


def one_step_errors(run, data, split: str = "test", limit: int | None = None, symmetrize: bool = False,
                    autocast: str = "none", physics: bool = False) -> dict:
    """{"contact": {...}, "airborne": {...}, "contact_share_of_rotation_error": float, "by_shape":
    {shape: {"contact": {...}, "airborne": {...}}}} where each part holds the mean position error (% of size) and rotation error (degrees) of one step,
    the 50/90/99th percentiles of the rotation error and the number of steps. A model with
    collision edges adds "objects_near"; `physics` adds "physics": the same parts for PyBullet
    from each step's history (physics_from_history)."""
    sim, saved = load_simulator(run, options=RolloutOptions(symmetrize=symmetrize, autocast=autocast))
    sim.eval()
    spec = ModelSpec.from_dict(saved["spec"])
    ds, scenes = load_split(data, split, limit, spec.frame_rate)
    if physics:
        toss_settings(ds)
    tracks = ObjectTracks(scenes, sim.mesh_library(ds.meshes), name=f"{split} split")
    frames = int(tracks.length.min())
    which = torch.arange(tracks.num_tracks)
    graph, verts, centres = tracks.track_vertices(which, frames)
    _, true_rot = tracks.poses(which, torch.zeros_like(which), frames)
    g = torch.as_tensor(ds.gravity, dtype=torch.float64) / ds.frame_rate ** 2
    contact = in_contact(centres, g, CONTACT)[:, 2:frames - 1].T.numpy()   # (steps, tracks): frame t -> t+1
    rot, pos, turned, true_turn, near = [], [], [], [], []
    with torch.no_grad():
        for t in range(2, frames - 1):
            if sim.layout.collisions:
                edges = sim.collision_edges(verts[:, t], graph)
                near.append(torch.zeros(tracks.num_tracks, dtype=torch.bool).index_fill(
                    0, graph.node_graph.index_select(0, edges.receivers), True).numpy())
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

    def stats(mask: np.ndarray, pos=pos, rot=rot) -> dict:
        return {"steps": int(mask.sum()),
                "position_error_pct": float(pos[mask].mean()) if mask.any() else None,
                "position_median_pct": float(np.median(pos[mask])) if mask.any() else None,
                "rotation_error_deg": float(rot[mask].mean()) if mask.any() else None,
                "rotation_percentiles_50_90_99": np.percentile(rot[mask], [50, 90, 99]).tolist()
                if mask.any() else None,
                # the angle turned in one step, predicted over true (summed): below 1, the
                # model turns objects too little from the true history, a bias a rollout adds up
                "spin_ratio": float(turned[mask].sum() / max(true_turn[mask].sum(), 1e-300)) if mask.any() else None}
    parts = {"contact": contact, "airborne": ~contact}
    if near:
        parts["objects_near"] = np.array(near)
    out = {name: stats(mask) for name, mask in parts.items()}
    if physics:
        p_pos, p_rot = physics_from_history(ds, scenes, frames)
        p_pos = 100.0 * p_pos / width[None, :]
        out["physics"] = {name: {k: v for k, v in stats(mask, p_pos, p_rot).items() if k != "spin_ratio"}
                          for name, mask in parts.items()}
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
    ap.add_argument("--physics", action="store_true",
                    help="also step PyBullet from each step's history (a datagen toss dataset): the errors the history leaves")
    ap.add_argument("--json", help="also write the result here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    res = {}
    status = guarded(lambda: res.update(one_step_errors(args.run, args.data, args.split, args.limit, args.symmetrize,
                                                        args.autocast, args.physics)))
    if status:
        return status
    print(f"{'':14s}{'steps':>7s}  {'position % of size (median)':29s}{'rotation deg (50/90/99%)':32s}spin ratio")
    for name in ("contact", "airborne", "objects_near"):
        for who, r in ((name.replace("_", " "), res.get(name)), ("  PyBullet", res.get("physics", {}).get(name))):
            if r and r["steps"]:
                p50, p90, p99 = r["rotation_percentiles_50_90_99"]
                position = f"{r['position_error_pct']:.3g} ({r['position_median_pct']:.3g})"
                rotation = f"{r['rotation_error_deg']:.3g} ({p50:.3g} / {p90:.3g} / {p99:.3g})"
                spin = f"{r['spin_ratio']:.3f}" if "spin_ratio" in r else ""
                print(f"{who:14s}{r['steps']:7d}  {position:29s}{rotation:32s}{spin}")
    if "physics" in res:
        print("PyBullet: the dataset's engine stepped from each step's history (velocities by finite differences)")
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
