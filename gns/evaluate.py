"""Judge a trained run on a dataset: rollouts, metrics, plots. Used by `gns eval` and pipelines."""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from plumbing import atomic_file, check_writable, DataError
from datagen.shards import Dataset
from gns.metrics import DEFAULT_HORIZONS, PROTOCOLS, evaluate_scenes, per_frame_curves, per_scene_means, scene_errors
from gns.rollout import diverged_line, split_diverged, timed_rollout, upsample_scene
from gns.data import feature_spec
from gns.network import HISTORY
from gns.spec import RolloutOptions
from gns.spec import outside_training
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec
from gns.checkpoint import checkpoint_of, load_simulator, parse_device
from gns.checkpoint import default_options


def _worst_first(per_scene: list[float]) -> list[int]:
    return list(np.argsort(per_scene)[::-1])


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
                 **changes) -> tuple[dict, list, list, Dataset]:
    """Roll out every scene of a split from its first 3 frames and score it, rolled out with
    `options` (default: gns.checkpoint.default_options(run), a zoo model's scored ones), with `changes`
    (RolloutOptions fields, e.g. symmetrize="d1") on top.

    A model trained at every k-th frame rolls out at its own rate from frames 0, k, 2k; it is
    scored at those frames, or with `at_data_rate` at every frame of the data (its poses
    interpolated, gns.rollout.upsample_scene), i.e. at the same instants as any other simulator.

    protocol="240hz": the protocol of later MOVi-A work (scenes recorded at 240 Hz, errors at 50,
    75 and 100 frames of 240 Hz after the last given frame, RMSE in metres and degrees): the data
    must be recorded at 240 frames a second; the model is scored at every frame (at_data_rate).

    Returns (results, predicted scenes, true scenes, dataset). Results hold the metrics of
    gns.metrics.evaluate_scenes plus where they came from, how they were rolled out
    (options_record) and what the rollouts cost.
    """
    options = (default_options(run) if options is None else options).replace(**changes)
    if protocol is not None:
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
    if at_data_rate and ds.stride > 1:
        full = Dataset(data)
        truth = full.load(split, limit)
        pairs = [upsample_scene(p, ds.stride, truth[i], full.frame_rate) for p, i in zip(pred, kept, strict=True)]
        pred, scenes, ds = [p for p, _ in pairs], [t for _, t in pairs], full
    given = (HISTORY - 1) * model_stride + 1 if at_data_rate else HISTORY   # frames up to the last given one
    horizons = PROTOCOLS[protocol] if protocol else DEFAULT_HORIZONS
    results = score_predictions(pred, scenes, ds, seconds, plots_dir, horizons=horizons, num_given=given)
    results.update(run=str(run), protocol=protocol, checkpoint=str(ckpt), data=str(data), split=split, outside_training=warnings,
                   diverged_scenes=diverged, num_diverged=len(diverged), at_data_rate=at_data_rate,
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


def evaluate_baseline(data: str | Path, split: str = "test", params=None, limit: int | None = None,
                      plots_dir: str | Path | None = None, engine: str = "pybullet",
                      given: int = HISTORY) -> tuple[dict, list, list, Dataset]:
    """`evaluate_run` for an analytic baseline (baselines: "pybullet" or "mujoco"): every
    one-cube scene of a split simulated from its first `given` frames with `params` (default: the
    engine's defaults, for PyBullet the published ContactNets constants), scored the same way.
    Returns (results, predicted, true, dataset)."""
    from baselines import baseline_engine  # the engines only when asked for
    params_class, simulate, _ = baseline_engine(engine)
    params = params_class() if params is None else params
    ds, scenes = load_split(data, split, limit)
    t0 = time.perf_counter()
    try:
        pred = [simulate(sc, params, frame_rate=ds.frame_rate, given=given) for sc in scenes]
    except ValueError as e:
        raise DataError(f"{data}: {e}") from None
    results = score_predictions(pred, scenes, ds, time.perf_counter() - t0, plots_dir)
    results.update(baseline=engine, params=params.to_dict(), data=str(data), split=split, given_frames=given)
    return results, pred, scenes, ds


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


def check_protocol(protocol: str, data: str | Path) -> None:
    """Refuse, in one line, a protocol this code does not know or data it cannot be scored on."""
    if protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}")
    rate = Dataset(data).frame_rate
    if abs(rate - 240) > 1e-9:
        raise DataError(f"{data}: the 240hz protocol needs scenes recorded at 240 frames a second, these are at "
                        f"{rate:g} (datagen toss --set scene.frame_rate=240 scene.frames=461 records MOVi-A's 2 s)")


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
        write_plots(plots_dir, pred, scenes, ds, results, errors=errors)
    return results


def write_plots(out: str | Path, pred: list, true: list, ds: Dataset, results: dict, count: int = 2,
                errors: list[dict] | None = None) -> list[Path]:
    """Figure-1 views and a GIF of the best and worst scenes, and error against time.
    `errors`: gns.metrics.scene_errors of pred against true, if already computed."""
    from gns.plots import animate_rollout, plot_error_vs_time, plot_trajectory
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    if errors is None:
        errors = scene_errors(pred, true, ds.meshes, floor_z)
    scores = [float(np.mean(f["position_error_pct"])) for f in errors]
    order = _worst_first(scores)
    picks = {"best": order[-1], "worst": order[0]}
    if len(order) > 2:
        picks["median"] = order[len(order) // 2]
    paths = []
    unit = ds.meta.get("units", "")
    unit = "half-widths" if "half-width" in unit else unit
    for name, i in list(picks.items())[:max(count, 1) + 1]:
        paths.append(plot_trajectory(pred[i], true[i], ds.meshes, out / f"trajectory_{name}.png", dt=ds.dt,
                                     floor_z=floor_z, unit=unit,
                                     title=f"{name} scene ({scores[i]:.1f}% position error): prediction vs truth"))
    curves = per_frame_curves(pred, true, ds.meshes, floor_z, errors=errors)
    paths.append(plot_error_vs_time({k: v for k, v in curves.items() if k != "count"}, out / "error_vs_time.png", dt=ds.dt))
    worst = picks["worst"]
    paths.append(animate_rollout(pred[worst], true[worst], ds.meshes, out / "rollout_worst.gif", fps=min(ds.frame_rate, 24),
                                 floor_z=floor_z, max_frames=120))
    return paths
