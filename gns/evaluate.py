"""A trained model judged on a dataset: its rollouts of a split's scenes, batched, and their scores
(`gns eval`, and the pipelines); `gns rollout` writes the same rollouts (gns.rollout_dataset).

Each object track starts from its first 3 true frames and runs on its own predictions to the
end of its scene. All objects of a scene are rolled out together (collision edges between them
are rebuilt from the predictions every step), and scenes of similar length share one packed
graph, so a batch of scenes costs about one network call per step. Vertex positions are integrated in
float64; poses (centre, quaternion) are recovered from the predicted vertices by shape matching
(with shape matching on, the vertices already are that rigid pose). The scores are gns.metrics'.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from plumbing import atomic_file, check_writable, DataError
from datagen.shards import Dataset, Scene, continuous, rotation
from gns.checkpoint import checkpoint_of, default_options, load_simulator, parse_device
from gns.data import ObjectTracks, feature_spec
from gns.geometry import matrix_to_quat
from gns.graph import ragged_arange
from gns.metrics import DEFAULT_HORIZONS, PROTOCOLS, evaluate_scenes, per_scene_means, scene_errors
from gns.network import HISTORY
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec, RolloutOptions, outside_training


# Rollouts, batched over a dataset's scenes: the same for `gns eval`, `gns rollout` and the pipelines.


def angular_velocities(quat: np.ndarray, dt: float) -> np.ndarray:
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


@torch.inference_mode()   # ~2-4% off a MOVi-A rollout against no_grad; only numpy leaves it
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
    _, rot, centre = sim.rollout(verts.to(device), graph.to(device), length - HISTORY, poses=True,
                                 live_steps=(tracks.length[which] - HISTORY).to(device))
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
        batch = torch.tensor(batch_scenes)
        owner, k = ragged_arange(tracks.scene_num_tracks[batch])   # each scene's tracks, in order
        ids = tracks.scene_first_track[batch][owner] + k
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

    Tracks of different lengths share a batch: each batch runs to its longest track, and the
    others are held still and left out of the network call once they end. Real tosses have nearly as many lengths as tosses (80-442 frames), and a
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
    # MOVi-A rollout's time (frames past a scene's end are NaN and stay out of its slice); the
    # velocities and which frames are finite likewise, sliced per scene below
    spin = angular_velocities(quaternions, dt)
    velocity = np.empty_like(positions)
    velocity[1:] = (positions[1:] - positions[:-1]) / dt
    ok = np.isfinite(positions).all(-1) & np.isfinite(quaternions).all(-1)   # (T_max, tracks)
    for sc in scenes:
        T, N = sc.num_frames, sc.num_objects
        pos, quat = positions[:T, first:first + N], quaternions[:T, first:first + N]
        vel = velocity[:T, first:first + N].copy()
        vel[:HISTORY] = sc.velocities[:HISTORY]
        frame_ok = ok[:T, first:first + N].all(-1)
        finite = bool(frame_ok.all())
        ang = spin[:T, first:first + N].copy() if finite else np.full_like(pos, np.nan)
        ang[:HISTORY] = sc.angular_velocities[:HISTORY]
        attrs = {**sc.attrs, "rollout": True}
        if not finite:
            attrs["diverged_at_frame"] = int(np.argmax(~frame_ok))
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




# Scores, and what every result records of how it was made and where it came from.


def write_json(path: str | Path, obj) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, mode=0o644) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=float) + "\n")


def options_record(sim: LearnedSimulator) -> dict:
    """What a rollout records of how it was made: its options whole (`rollout_options`), and the
    same flattened as earlier result files hold them, with what `auto` and the clearance resolved to."""
    o = sim.options
    return {"rollout_options": o.to_dict(), "shape_matching": o.shape_matching, "symmetrize": o.symmetry_group,
            "body_frames": o.body_frames, "free_flight": o.free_flight,
            "free_clearance": sim.free_flight_clip if o.free_flight else None,
            "sleep": None if sim.sleep is None else dataclasses.asdict(sim.sleep), "autocast": o.autocast,
            "autocast_used": sim.autocast_used, "compile": o.compile, "ensemble": list(o.ensemble)}


def evaluate_run(run: str | Path, data: str | Path, split: str = "test", limit: int | None = None,
                 options: RolloutOptions | None = None, plots_dir: str | Path | None = None, progress: bool = True,
                 at_data_rate: bool = False, device: str = "cpu", protocol: str | None = None,
                 between: str = "learned", **changes) -> tuple[dict, list, list, Dataset]:
    """Roll out every scene of a split from its first 3 frames and score it, rolled out with
    `options` (default: gns.checkpoint.default_options(run), a zoo model's scored ones), with `changes`
    (RolloutOptions fields, e.g. symmetrize="d1") on top.

    A model trained at every k-th frame rolls out at its own rate from frames 0, k, 2k; it is
    scored at those frames, or with `at_data_rate` at every frame of the data (its poses
    read between its steps, gns.at_data_rate.upsample_scene), i.e. at the same instants as any other simulator:
    with `between` "learned" by the reader between steps the model file holds (gns.between), by a
    cubic spline where it holds none or with "spline".

    protocol="240hz": the protocol of later MOVi-A work (scenes recorded at 240 Hz, errors at 50,
    75 and 100 frames of 240 Hz after the last given frame, RMSE in metres and degrees): the data
    must be recorded at 240 frames a second; the model is scored at every frame (at_data_rate).

    Returns (results, predicted scenes, true scenes, dataset). Results hold the metrics of
    gns.metrics.evaluate_scenes plus where they came from, how they were rolled out
    (options_record) and what the rollouts cost.
    """
    options = (default_options(run) if options is None else options).replace(**changes)
    if protocol is not None:
        from gns.at_data_rate import check_protocol
        check_protocol(protocol, data)
        at_data_rate = True
    device = parse_device(device, "--device")
    ckpt = checkpoint_of(run)
    sim, saved = load_simulator(ckpt, device, options)
    if plots_dir is not None:
        check_writable(plots_dir, "plots folder")
    spec = ModelSpec.from_dict(saved["spec"])
    ds, scenes = load_split(data, split, limit, spec.frame_rate)
    warnings = check_ranges(spec, ds, scenes)
    pred, seconds, warmup = timed_rollout(sim, scenes, ds.meshes, ds.frame_rate, progress)
    counts = dict(sim.rollout_counts)
    kept = [i for i, p in enumerate(pred) if "diverged_at_frame" not in p.attrs]
    pred, scenes, diverged = split_diverged(pred, scenes)
    if diverged:
        _warn(diverged_line(diverged, len(scenes) + len(diverged), "left out of the metrics"))
    model_stride = ds.stride
    read_by = None
    if at_data_rate and ds.stride > 1:
        from gns.at_data_rate import read_split_at_data_rate
        pairs, ds, read_by = read_split_at_data_rate(pred, kept, saved, between, data, split, limit, ds.stride)
        pred, scenes = [p for p, _ in pairs], [t for _, t in pairs]
    given = (HISTORY - 1) * model_stride + 1 if at_data_rate else HISTORY   # frames up to the last given one
    horizons = PROTOCOLS[protocol] if protocol else DEFAULT_HORIZONS
    results = score_predictions(pred, scenes, ds, seconds, plots_dir, horizons=horizons, num_given=given)
    results.update(run=str(run), protocol=protocol, checkpoint=str(ckpt), data=str(data), split=split, outside_training=warnings,
                   diverged_scenes=diverged, num_diverged=len(diverged), at_data_rate=at_data_rate, read_between=read_by,
                   model_stride=model_stride, object_steps=counts, warmup_seconds=warmup, device=str(device),
                   **options_record(sim), **provenance_of(saved, ds))
    return results, pred, scenes, ds


def provenance_of(saved: dict, ds: Dataset) -> dict:
    """What an evaluation or rollout records of where it came from: this code's versions and
    commit, the fingerprint of the data it ran on, and of the data the model was trained on
    (None for a checkpoint written before runs recorded it), so a mismatch can be seen."""
    from plumbing import provenance
    trained = saved.get("provenance") if isinstance(saved.get("provenance"), dict) else {}
    return {"provenance": provenance(), "data_fingerprint": ds.fingerprint,
            "trained_on_fingerprint": (trained.get("data") or {}).get("fingerprint")}


def _warn(line: str) -> None:
    print(line, file=sys.stderr)


def check_ranges(trained_spec: ModelSpec, ds: Dataset, scenes: list, warn=None) -> list[str]:
    """Warn (stderr, one line each) where the scenes leave a checkpoint's training ranges
    (its `spec`)."""
    problems = outside_training(trained_spec, feature_spec(ds, scenes))
    for p in problems:
        (warn or _warn)(f"warning: outside training: {p}")
    crowded = sum(sc.num_objects > 1 for sc in scenes)
    if crowded and not trained_spec.collision_edges:
        # not an "outside training" range: the model cannot represent contact between objects at all
        (warn or _warn)(f"warning: {crowded} of {len(scenes)} scenes hold several objects, but the model was trained "
                        "on single-object scenes and has no collision edges: objects will pass through each other "
                        "(--keep-apart translates them apart: a projection, not learned contact)")
    return problems


def load_split(data: str | Path, split: str, limit: int | None,
               frame_rate: float | None = None) -> tuple[Dataset, list]:
    """Scenes of a split. Given a model's `frame_rate`, data recorded at a whole multiple of it
    are read at that rate (every k-th frame); any other rate is left for check_ranges to flag.
    Refuses shards changed since they were written (verify_shards)."""
    if limit is not None and limit < 1:
        raise DataError(f"--limit must be >= 1 scene, got {limit}")
    ds = Dataset(data)
    verify_shards(ds)
    if frame_rate:
        ratio = ds.frame_rate / frame_rate
        if round(ratio) > 1 and abs(ratio - round(ratio)) < 1e-6:
            ds = Dataset(data, stride=round(ratio))
    if split not in ds.splits:
        raise DataError(f"{data}: no scenes in split {split!r}; it has {', '.join(ds.splits) or 'none'}")
    return ds, ds.load(split, limit)


def verify_shards(ds: Dataset) -> None:
    """Refuse a dataset whose shards changed since they were written: every shard metadata.json
    records a checksum of is hashed again (sha256, ~1 GB/s: a small cost beside reading and
    rolling out the same bytes), so that no result records a fingerprint that does not describe
    the data it scored (datagen inspect reports the same, exit 3). Listed shards that are missing
    are left to the reader (a split not read may be absent); a dataset written before checksums
    were recorded has nothing to compare against (its fingerprint is computed from the shards)."""
    from plumbing import file_sha256
    recorded = ds.meta.get("checksums")
    if not isinstance(recorded, dict):
        return
    for name, digest in sorted(recorded.items()):
        path = ds.root / name
        if path.is_file() and file_sha256(path) != digest:
            raise DataError(f"{path} changed since it was written (its sha256 is not the checksum metadata.json "
                            f"records), so the dataset's fingerprint no longer describes it; run `datagen inspect "
                            f"{ds.root}`")


def score_predictions(pred: list, scenes: list, ds: Dataset, seconds: float,
                      plots_dir: str | Path | None = None, horizons=DEFAULT_HORIZONS, num_given: int = HISTORY) -> dict:
    """Metrics (gns.metrics.evaluate_scenes) of predicted scenes against the truth, what the
    predictions cost, per-scene means (`per_scene`, for paired comparisons), and plots if asked.
    horizons count frames after the num_given-th (the last given) frame."""
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    errors = scene_errors(pred, scenes, ds.meshes, floor_z)
    results = evaluate_scenes(pred, scenes, ds.meshes, floor_z=floor_z, errors=errors, horizons=horizons,
                              num_given=num_given)
    simulated = sum((sc.num_frames - HISTORY) / ds.frame_rate for sc in scenes)
    results.update(rollout_seconds=seconds, simulated_seconds=simulated,
                   wall_seconds_per_simulated_second=seconds / simulated if simulated else None,
                   per_scene=per_scene_means(pred, scenes, ds.meshes, floor_z, errors=errors))
    if plots_dir is not None:
        from gns.plots import write_plots
        write_plots(plots_dir, pred, scenes, ds, results, errors=errors)
    return results
