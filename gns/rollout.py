"""Batched rollouts of a trained simulator over the scenes of a dataset, and their poses.

Each object track starts from its first 3 true frames and runs on its own predictions to the
end of its scene. All objects of a scene are rolled out together (collision edges between them
are rebuilt from the predictions every step), and scenes of similar length share one packed
graph, so a batch of scenes costs about one network call per step. Vertex positions are integrated in
float64; poses (centre, quaternion) are recovered from the predicted vertices by shape matching
(with shape matching on, the vertices already are that rigid pose).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from plumbing import check_output_folder, check_writable, DataError, overlapping
from datagen.shards import continuous
from datagen.shards import rotation, wxyz
from datagen.shards import Dataset, Scene, shard_name, write_metadata, write_shard
from gns.data import ObjectTracks
from gns.network import HISTORY
from gns.geometry import matrix_to_quat
from gns.simulator import LearnedSimulator


def _angular_velocity(quat: np.ndarray, dt: float) -> np.ndarray:
    """World-frame angular velocity (T, N, 3) from orientations (T, N, 4) wxyz, backward differences."""
    out = np.zeros(quat.shape[:-1] + (3,))
    flat = quat.reshape(-1, 4)
    # a diverged rollout has non-finite (or zero) quaternions: NaN there, not a scipy error
    good = np.isfinite(flat).all(axis=1) & (np.linalg.norm(np.nan_to_num(flat), axis=1) > 0)
    rot = np.full((len(flat), 3, 3), np.nan)
    rot[good] = rotation(flat[good]).as_matrix()
    rot = rot.reshape(quat.shape[:-1] + (3, 3))
    rel = (rot[1:] @ np.swapaxes(rot[:-1], -1, -2)).reshape(-1, 3, 3)
    ok = np.isfinite(rel).all(axis=(1, 2))
    vec = np.full((len(rel), 3), np.nan)
    vec[ok] = Rotation.from_matrix(rel[ok]).as_rotvec()
    out[1:] = vec.reshape((quat.shape[0] - 1, *quat.shape[1:-1], 3)) / dt
    return out


@torch.no_grad()
def rollout_tracks(sim: LearnedSimulator, tracks: ObjectTracks, which: torch.Tensor,
                   length: int) -> tuple[np.ndarray, np.ndarray]:
    """Roll out tracks `which` (B,), all `length` frames long, as sim.options ask. Tracks of one
    scene interact (collision edges), so pass every track of the scenes wanted.

    Returns centres (length, B, 3) and quaternions (length, B, 4): the first 3 frames are the
    truth, the rest predicted.
    """
    graph, verts, _ = tracks.track_vertices(which, HISTORY)
    device = next(sim.parameters()).device
    # the whole rollout runs on the model's device; only the poses come back
    # the poses come from the rollout's own shape matching (one per step, not a second pass)
    _, rot, centre = sim.rollout(verts.to(device), graph.to(device), length - HISTORY, poses=True)
    rot, centre = rot.cpu(), centre.cpu()
    idx = (tracks.start[which])[:, None] + torch.arange(HISTORY)
    true_pos = tracks.positions[idx].permute(1, 0, 2).numpy()
    true_quat = tracks.quaternions[idx].permute(1, 0, 2).numpy()
    positions = np.concatenate([true_pos, centre.numpy()])
    with np.errstate(invalid="ignore", divide="ignore"):
        quaternions = np.concatenate([true_quat, matrix_to_quat(rot.numpy())])
    # A diverged track (a vertex went to inf or NaN) has no pose from then on: NaN, not the
    # identity rotation or zero quaternion that shape matching and matrix_to_quat make of it.
    bad = np.maximum.accumulate(~np.isfinite(positions).all(-1) | ~np.isfinite(quaternions).all(-1), axis=0)
    positions[bad] = np.nan
    quaternions[bad] = np.nan
    return positions, continuous(quaternions)


def rollout_scenes(sim: LearnedSimulator, scenes: list[Scene], meshes: dict, frame_rate: float,
                   progress: bool = True) -> list[Scene]:
    """Predicted copies of `scenes`: same objects, poses rolled out from the first 3 frames as
    sim.options ask (LearnedSimulator.rollout), sim.options.batch objects at a time; the share of
    object-steps that entered the network is left in `sim.rollout_counts` (summed over batches)."""
    sim.eval()
    tracks = ObjectTracks(scenes, sim.mesh_library(meshes), name="rollout scenes")
    if int(tracks.length.min()) <= HISTORY:
        raise DataError(f"every scene needs more than {HISTORY} frames to roll out")
    T_max, B = int(tracks.length.max()), tracks.num_tracks
    positions = np.full((T_max, B, 3), np.nan)
    quaternions = np.full((T_max, B, 4), np.nan)
    bar = tqdm(total=B, unit="track", desc="rollout", disable=not progress)
    counts: dict[str, int] = {}
    for batch_scenes in scene_batches(scenes, sim.options.batch):
        ids = torch.cat([tracks.scene_first_track[i] + torch.arange(int(tracks.scene_num_tracks[i]))
                         for i in batch_scenes])
        lengths = tracks.length[ids].tolist()
        p, q = rollout_tracks(sim, tracks, ids, max(lengths))
        for key, value in sim.rollout_counts.items():
            counts[key] = counts.get(key, 0) + value
        for j, (i, length) in enumerate(zip(ids.tolist(), lengths)):
            positions[:length, i] = p[:length, j]
            quaternions[:length, i] = q[:length, j]
        bar.update(len(ids))
    bar.close()
    sim.rollout_counts = counts
    return predicted_scenes(scenes, positions, quaternions, 1.0 / frame_rate)


def timed_rollout(sim: LearnedSimulator, scenes: list[Scene], meshes: dict, frame_rate: float,
                  progress: bool = True) -> tuple[list[Scene], float, float | None]:
    """rollout_scenes, its wall-clock seconds, and (with sim.options.compile) the seconds of a first
    batch rolled out before the clock starts: a compiled network compiles at its first calls (tens
    of seconds on a CPU, several times the rollouts of 400 MOVi-A scenes), which the timed rollout
    should not count. Nothing of the first batch is kept but the compiled graphs (rollout_scenes
    resets the counts)."""
    warmup = None
    if sim.options.compile:
        t0 = time.perf_counter()
        first = scene_batches(scenes, sim.options.batch)[0]
        rollout_scenes(sim, [scenes[i] for i in first], meshes, frame_rate, progress=False)
        warmup = time.perf_counter() - t0
    t0 = time.perf_counter()
    pred = rollout_scenes(sim, scenes, meshes, frame_rate, progress=progress)
    return pred, time.perf_counter() - t0, warmup


def scene_batches(scenes: list[Scene], batch_tracks: int) -> list[list[int]]:
    """Scene indices in batches of about `batch_tracks` objects, shortest scenes first.

    Tracks of different lengths share a batch: each batch runs to its longest track and the
    others are cut. Real tosses have nearly as many lengths as tosses (80-442 frames), and a
    network call costs about the same for 1 or 100 small graphs, so one batch per length
    would cost the sum of the lengths in calls instead of the longest.
    All objects of a scene are rolled out together (one batch), so collision edges between
    them are rebuilt from the predicted positions at every step: batches hold whole scenes."""
    scene_length = torch.tensor([sc.num_frames for sc in scenes])
    order = torch.argsort(scene_length, stable=True).tolist()
    batches, current, objects = [], [], 0
    for i in order:
        current.append(i)
        objects += scenes[i].num_objects   # a running count: summing the batch again made this quadratic
        if objects >= batch_tracks:
            batches.append(current)
            current, objects = [], 0
    if current:
        batches.append(current)
    return batches


def predicted_scenes(scenes: list[Scene], positions: np.ndarray, quaternions: np.ndarray, dt: float) -> list[Scene]:
    """Copies of `scenes` holding the predicted poses (T_max, all tracks, 3 or 4), velocities by
    finite differences (the given frames' own), and `diverged_at_frame` where a pose is not finite."""
    out, first = [], 0
    # one call over every track, not one a scene: scipy's per-call overhead was ~5% of a batched
    # MOVi-A rollout's time (frames past a scene's end are NaN and stay out of its slice)
    spin = _angular_velocity(quaternions, dt)
    for sc in scenes:
        T, N = sc.num_frames, sc.num_objects
        pos, quat = positions[:T, first:first + N], quaternions[:T, first:first + N]
        vel = np.zeros_like(pos)
        vel[1:] = (pos[1:] - pos[:-1]) / dt
        vel[:HISTORY] = sc.velocities[:HISTORY]
        finite = np.isfinite(pos).all() and np.isfinite(quat).all()
        ang = spin[:T, first:first + N].copy() if finite else np.full_like(pos, np.nan)
        ang[:HISTORY] = sc.angular_velocities[:HISTORY]
        attrs = {**sc.attrs, "rollout": True}
        if not finite:
            attrs["diverged_at_frame"] = int(np.argmax(~(np.isfinite(pos).all((-1, -2)) & np.isfinite(quat).all((-1, -2)))))
        out.append(Scene(positions=pos, quaternions=quat, velocities=vel, angular_velocities=ang,
                         shape=list(sc.shape), material=list(sc.material), scale=sc.scale.copy(),
                         mass=sc.mass.copy(), friction=sc.friction.copy(), restitution=sc.restitution.copy(),
                         attrs=attrs))
        first += N
    return out


class DivergedError(Exception):
    """Every rollout went to inf or NaN: nothing to score or write. One line for a user."""


def scene_label(scene: Scene, index: int):
    """A scene's id for reports: its scene_id attribute, else its index in the split."""
    sid = scene.attrs.get("scene_id", index)
    return sid.item() if hasattr(sid, "item") else sid


def split_diverged(pred: list[Scene], true: list[Scene]) -> tuple[list[Scene], list[Scene], list]:
    """(finite predictions, their true scenes, ids of the scenes whose rollout diverged).

    Raises DivergedError when every rollout diverged."""
    ok = [i for i, p in enumerate(pred) if "diverged_at_frame" not in p.attrs]
    diverged = [scene_label(true[i], i) for i in range(len(pred)) if "diverged_at_frame" in pred[i].attrs]
    if not ok:
        raise DivergedError(f"every rollout diverged ({len(pred)} scenes: positions became inf or NaN); "
                            "the model is unstable on this data")
    return [pred[i] for i in ok], [true[i] for i in ok], diverged


def diverged_line(diverged: list, total: int, what: str) -> str:
    shown = ", ".join(map(str, diverged[:10])) + (f" and {len(diverged) - 10} more" if len(diverged) > 10 else "")
    return f"warning: {len(diverged)} of {total} rollouts diverged (inf or NaN positions), {what}: {shown}"


def check_flags(**flags) -> None:
    """Numeric rollout flags (`gns rollout`, `gns eval`) out of range ({dest: value}, None when
    unset): one line naming the flag, before the model or the data are read."""
    rules = {"batch": (lambda v: v >= 1, "a whole number >= 1"), "limit": (lambda v: v >= 1, ">= 1 scene"),
             "sleep_fraction": (lambda v: math.isfinite(v) and v > 0, "a finite number > 0"),
             "free_clearance": (lambda v: math.isfinite(v) and v >= 0, "a finite height >= 0 above the floor")}
    for dest, value in flags.items():
        ok, want = rules[dest]
        if value is not None and not ok(value):
            raise DataError(f"--{dest.replace('_', '-')} must be {want}, got {value:g}")


def check_output(out: str | Path, overwrite: bool, data: str | Path | None = None) -> Path:
    """Refuse, before any work is done: an output folder that is, holds or lies in the input
    dataset `data`; an existing non-empty folder without `overwrite`; with `overwrite`, a
    folder that is not an earlier `gns rollout` output (only files this tool wrote are replaced);
    a folder that cannot be written."""
    out = Path(out)
    if data is not None and overlapping(out, data):
        raise DataError(f"--out {out} and --data {data} overlap (the same folder or one inside the other); "
                        "write the rollouts to a folder of their own")
    if not overwrite and _unfinished_rollout(out):
        raise DataError(f"--out {out} holds an unfinished gns rollout (shards without metadata.json: it was stopped "
                        "before the end); use --overwrite to replace it")
    if check_output_folder(out, overwrite, "use --overwrite to replace it"):
        _rollout_files(out)
    return check_writable(out)


def _rollout_files(out: Path) -> list[Path]:
    """The files an earlier `gns rollout` wrote into `out` (its metadata.json and the shards it
    lists, or the shards of one stopped before its metadata.json); DataError if `out` holds
    anything else, so --overwrite deletes nothing else."""
    unfinished = _unfinished_rollout(out)
    if unfinished:
        return unfinished
    try:
        meta = json.loads((out / "metadata.json").read_text())
        listed = [out / name for split in meta["splits"].values() for name in split["shards"]]
        ours = meta.get("generator") == "gns rollout"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        ours, listed = False, []
    if not ours:
        raise DataError(f"--overwrite only replaces an earlier gns rollout output, and {out} is not one "
                        "(no metadata.json written by gns rollout); choose another --out")
    names = {p.name for p in listed} | {"metadata.json"}
    others = sorted(p.name for p in out.iterdir() if p.name not in names)
    if others:
        raise DataError(f"--overwrite refuses {out}: besides an earlier rollout it holds {', '.join(others[:4])}"
                        f"{' ...' if len(others) > 4 else ''}; choose another --out")
    return [p for p in listed if p.exists()] + [out / "metadata.json"]


def _unfinished_rollout(out: Path) -> list[Path]:
    """The files of a `gns rollout` stopped before writing metadata.json (its last file): every
    file in `out` is a shard gns rollout wrote (a shard name, `rollout` set in the file's
    attributes) or a temporary file of the atomic writer under one of the format's names; [] if
    `out` is anything else."""
    import h5py
    from datagen.shards import dataset_files
    if not out.is_dir() or (out / "metadata.json").exists():
        return []
    entries = list(out.iterdir())
    ours = {p.name for p in dataset_files(out)}
    if not entries or any(p.name not in ours for p in entries):
        return []
    for p in entries:
        if p.name.startswith("."):   # a temporary file: torn by construction, nothing to read
            continue
        try:
            with h5py.File(p, "r") as f:
                if not f.attrs.get("rollout"):
                    return []
        except OSError:
            return []
    return entries


def write_rollouts(out: str | Path, scenes: list[Scene], source: Dataset, split: str, info: dict,
                   overwrite: bool = False, per_shard: int = 64) -> None:
    """Rollouts as a dataset in the documented format (the same reader reads them). Diverged
    rollouts (no finite pose) are left out and listed in the metadata as rollout.diverged."""
    out = check_output(out, overwrite, source.root)
    kept = [sc for sc in scenes if "diverged_at_frame" not in sc.attrs]
    diverged = [scene_label(sc, i) for i, sc in enumerate(scenes) if "diverged_at_frame" in sc.attrs]
    if not kept:
        raise DivergedError(f"every rollout diverged ({len(scenes)} scenes: positions became inf or NaN); "
                            f"nothing written to {out}")
    if out.exists() and any(out.iterdir()):
        for p in _rollout_files(out):
            p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    meshes = source.meshes
    names = []
    for k in range(math.ceil(len(kept) / per_shard)):
        name = shard_name(split, k)
        write_shard(out / name, kept[k * per_shard:(k + 1) * per_shard], meshes, attrs={"split": split, "rollout": 1})
        names.append(name)
    meta = {key: v for key, v in source.meta.items() if key not in ("splits", "format_version", "complete")}
    meta.update(generator="gns rollout", rollout={**info, "diverged": diverged}, frame_rate=source.frame_rate,
                splits={split: {"num_scenes": len(kept), "shards": names}})
    write_metadata(out, meta)


def upsample_scene(pred: Scene, stride: int, true: Scene, frame_rate: float) -> tuple[Scene, Scene]:
    """A rollout made at every `stride`-th frame, interpolated to every frame of the full-rate
    truth it covers: centres by a cubic spline (exact for free flight's parabolas; a bounce's
    kink rings by a small fraction of one coarse step's motion), rotations by slerp. Returns (predicted, true), both cut to the frames up to the last predicted one, so a
    model with a coarser time step is scored at the same instants as one at the data's rate.
    frame_rate is the truth's (fine) rate."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Slerp

    coarse = np.arange(pred.num_frames) * stride
    fine = np.arange(coarse[-1] + 1)
    positions = CubicSpline(coarse, pred.positions, axis=0)(fine) if len(coarse) > 2 else \
        np.stack([np.interp(fine, coarse, c) for c in pred.positions.reshape(len(coarse), -1).T], -1).reshape(
            len(fine), *pred.positions.shape[1:])
    quaternions = np.empty((len(fine), pred.num_objects, 4))
    for n in range(pred.num_objects):
        slerp = Slerp(coarse, rotation(pred.quaternions[:, n]))
        quaternions[:, n] = continuous(wxyz(slerp(fine).as_quat()))
    dt = 1.0 / frame_rate
    velocities = np.zeros_like(positions)
    velocities[1:] = (positions[1:] - positions[:-1]) / dt
    velocities[0] = true.velocities[0]
    cut = len(fine)
    upsampled = Scene(positions=positions, quaternions=quaternions, velocities=velocities,
                      angular_velocities=_angular_velocity(quaternions, dt), shape=list(pred.shape),
                      material=list(pred.material), scale=pred.scale.copy(), mass=pred.mass.copy(),
                      friction=pred.friction.copy(), restitution=pred.restitution.copy(),
                      attrs={**pred.attrs, "upsampled_from_stride": stride})
    truth = Scene(*(getattr(true, k)[:cut] for k in ("positions", "quaternions", "velocities", "angular_velocities")),
                  list(true.shape), list(true.material), true.scale, true.mass, true.friction, true.restitution,
                  dict(true.attrs))
    return upsampled, truth
