"""How the zoo's real_cubes comes to rest: the cube's speed and spin against time, model against
truth, on the 96 held-out test tosses of its recipe.

    python -m pipelines.real_cubes_rest --src PATH/TO/contact-nets/data [--out DIR] [--figure PNG]

The test split is the recipe's own (pipelines.recipe.data_stage_of on configs/recipes/real_cubes.toml),
refused unless its training data has the recipe's fingerprint. The model is rolled out as
`gns eval --run real_cubes --data OUT/test --at-data-rate` does (its card's options) and its errors
scored at every recorded frame. Speed (m/s, from the centre's displacement) and spin (rad/s, from
the rotation between poses) are measured over each of the model's own steps (8 recorded frames,
54 ms), the truth read at the same frames, so both are differenced alike and no interpolated pose
enters them. A toss is read up to the last frame the model reaches, as gns eval does: 0-7 recorded
frames short of its end, where the tracked cube has just stopped.

Past that end the model is rolled out AFTER_STEPS further (the same rollout, the scenes padded with
their last recorded pose, which only lengthens it): how far it slides and turns on once the real
cube has stopped, against the truth's own jitter at rest (its two tosses recorded for a second
after they stop).

Writes OUT/report.md, OUT/results.json, OUT/rest.png (aligned at the end) and OUT/rest_start.png.
"""
from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np

from plumbing import DataError
from datagen.contactnets import HALF_WIDTH_M
from datagen.shards import Dataset
from gns.checkpoint import default_options, load_simulator
from gns.evaluate import evaluate_run, load_split, rollout_scenes, write_json
from gns.geometry import rotation_angle
from gns.metrics import scene_errors
from gns.network import HISTORY
from gns.spec import ModelSpec
from pipelines.common import guarded, say
from pipelines.recipe import data_stage_of, load_recipe

MODEL = "real_cubes"
# A window is the 30 (or 10) recorded frames (a, b]: errors at frames a+1..b, motion over the model
# steps with both ends in [a, b] (3 steps for 30 frames, 1 for 10, at a stride of 8).
WINDOW, LAST = 30, 10
# At rest over a model step: below both. The truth's jitter at rest (results.json
# "truth_jitter_at_rest") is ~0.0025 m/s and ~0.008 rad/s at its 99th percentile at this step; the
# thresholds are 2 and 6 times that and still small for a moving cube: 0.27 mm and 0.15 degrees a
# step, where a cube sliding to a stop loses ~0.1 m/s a step (friction ~0.2 g).
REST_SPEED = 0.005   # m/s
REST_SPIN = 0.05     # rad/s
JITTER_AFTER = 1.0   # s from release: every toss still recorded then has long stopped
AFTER_STEPS = 20     # model steps rolled out past the end (1.08 s)
AFTER_ROWS = (1, 2, 5, 10, 20)
PLOT_BEFORE, PLOT_AFTER = 10, 10   # model steps shown either side of the end (0.54 s each)


def speeds(positions: np.ndarray, dt: float, unit: float = 1.0) -> np.ndarray:
    """Speed over each interval of a track (T, 3) -> (T-1,), in `unit` (metres per data unit) per second."""
    return np.linalg.norm(np.diff(positions, axis=0), axis=1) * unit / dt


def spins(quaternions: np.ndarray, dt: float) -> np.ndarray:
    """Mean angular speed over each interval (rad/s) of orientations (T, 4) wxyz -> (T-1,): the
    angle of the rotation between successive poses over dt (a turn of more than pi a step aliases)."""
    return rotation_angle(quaternions[1:], quaternions[:-1]) / dt


def align_end(series: list[np.ndarray], n: int | None = None) -> np.ndarray:
    """Series of different lengths as rows (len, n) ending at the last column, NaN before their start."""
    n = max(map(len, series)) if n is None else n
    out = np.full((len(series), n), np.nan)
    for i, s in enumerate(series):
        k = min(n, len(s))
        if k:
            out[i, n - k:] = s[len(s) - k:]
    return out


def align_start(series: list[np.ndarray], n: int | None = None) -> np.ndarray:
    """Series of different lengths as rows (len, n) starting at the first column, NaN after their end."""
    return align_end([s[::-1] for s in series], n)[:, ::-1]


def band(rows: np.ndarray) -> dict:
    """Mean, median, quartiles and count over the rows (tosses) at each column, NaN-aware."""
    with warnings.catch_warnings():   # a column no toss reaches is NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        q25, median, q75 = np.nanpercentile(rows, [25, 50, 75], axis=0)
        mean = np.nanmean(rows, axis=0)
    return {"mean": mean, "median": median, "q25": q25, "q75": q75, "count": np.isfinite(rows).sum(axis=0)}


def toss_motion(positions: np.ndarray, quaternions: np.ndarray, stride: int, frame_rate: float,
                unit: float = HALF_WIDTH_M) -> dict:
    """Speed and spin of one recorded-rate track (T, 3), (T, 4) over each step of `stride` frames,
    read at frames 0, stride, ...; T - 1 must be a whole number of steps."""
    if (len(positions) - 1) % stride:
        raise ValueError(f"a track of {len(positions)} frames is no whole number of {stride}-frame steps")
    dt = stride / frame_rate
    return {"speed": speeds(positions[::stride], dt, unit), "spin": spins(quaternions[::stride], dt)}


def step_window(last_frame: int, a: int, b: int, stride: int) -> slice:
    """The steps (step j spans frames j*stride .. (j+1)*stride) with both ends in [a, b]."""
    first = -(-max(a, 0) // stride)
    return slice(first, max(first, min(b, last_frame) // stride))


def windows(last_frame: int, given: int) -> dict[str, tuple[int, int]]:
    """The windows (a, b] of recorded frames of a toss whose last frame the model reaches is last_frame."""
    mid = (given + last_frame) // 2
    return {"all frames (the card's score)": (-1, last_frame),
            f"first {WINDOW} after the given frames": (given, given + WINDOW),
            f"middle {WINDOW}": (mid - WINDOW // 2, mid + WINDOW // 2),
            f"last {WINDOW}": (last_frame - WINDOW, last_frame), f"last {LAST}": (last_frame - LAST, last_frame)}


def at_rest(speed, spin, factor: float = 1.0):
    return (np.asarray(speed) < factor * REST_SPEED) & (np.asarray(spin) < factor * REST_SPIN)


def measure(pred: list, truth: list, errors: list, stride: int, frame_rate: float) -> list[dict]:
    """Per toss: the model's and the truth's speed and spin over each predicted step, and each
    window's means of them and of the errors (gns.metrics.scene_errors at every recorded frame)."""
    tosses = []
    for p, t, e in zip(pred, truth, errors, strict=True):
        last = t.num_frames - 1
        motion = {who: toss_motion(s.positions[:, 0], s.quaternions[:, 0], stride, frame_rate)
                  for who, s in (("model", p), ("truth", t))}
        flat = {f"{who}_{k}": v for who, d in motion.items() for k, v in d.items()}
        row = {"scene_id": _plain(t.attrs.get("scene_id")), "frames": t.num_frames,
               "series": {k: v[HISTORY - 1:] for k, v in flat.items()}, "windows": {}}
        for name, (a, b) in windows(last, (HISTORY - 1) * stride).items():
            steps = step_window(last, a, b, stride)
            w = {k: float(v[steps].mean()) for k, v in flat.items()}
            w.update(steps=steps.stop - steps.start,
                     position_error_pct=float(e["position_error_pct"][a + 1:b + 1, 0].mean()),
                     rotation_error_deg=float(e["rotation_error_deg"][a + 1:b + 1, 0].mean()))
            row["windows"][name] = w
        end = row["windows"][f"last {LAST}"]
        row["truth_at_rest"] = bool(at_rest(end["truth_speed"], end["truth_spin"]))
        row["model_at_rest"] = bool(at_rest(end["model_speed"], end["model_spin"]))
        tosses.append(row)
    return tosses


def after_end(track: tuple, recorded, last_step: int, stride: int, frame_rate: float) -> dict:
    """One toss past the last frame the model reaches in it (step `last_step` of the model's
    `track`, poses (T', 3), (T', 4) at its own rate): its speed, spin, and the distance (mm) and
    angle (deg) it has moved since, at each step after; and the truth (`recorded`, every recorded
    frame) over its own last `stride` frames and from the model's last frame to its end."""
    pos, quat = track
    dt = stride / frame_rate
    tail_p, tail_q = pos[last_step:], quat[last_step:]
    rp, rq, cut = recorded.positions[:, 0], recorded.quaternions[:, 0], last_step * stride
    return {"model_speed": speeds(tail_p, dt, HALF_WIDTH_M), "model_spin": spins(tail_q, dt),
            "model_slid_mm": 1000 * HALF_WIDTH_M * np.linalg.norm(tail_p[1:] - tail_p[0], axis=1),
            "model_turned_deg": np.degrees(rotation_angle(tail_q[1:], np.broadcast_to(tail_q[0], tail_q[1:].shape))),
            "truth_end_speed": float(speeds(rp[[-1 - stride, -1]], dt, HALF_WIDTH_M)[0]),
            "truth_end_spin": float(spins(rq[[-1 - stride, -1]], dt)[0]),
            "truth_end_time_s": (len(rp) - 1 - stride / 2 - cut) / frame_rate,
            "truth_slid_mm": float(1000 * HALF_WIDTH_M * np.linalg.norm(rp[-1] - rp[cut])),
            "truth_turned_deg": float(np.degrees(rotation_angle(rq[-1], rq[cut])))}


def summarise(tosses: list[dict], after: list[dict], stride: int, frame_rate: float) -> dict:
    """Means over tosses (each weighs the same) per window, rest shares, curves aligned at the end
    and at the start (seconds, at the middle of each step), past the end, and the truth's jitter."""
    step = stride / frame_rate
    table = {}
    for name in tosses[0]["windows"]:
        rows = [t["windows"][name] for t in tosses]
        mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "steps"}
        for k in ("speed", "spin"):
            mean[f"{k}_ratio"] = mean[f"model_{k}"] / mean[f"truth_{k}"] if mean[f"truth_{k}"] > 0 else None
        mean["steps"] = [min(r["steps"] for r in rows), max(r["steps"] for r in rows)]
        table[name] = mean
    share = lambda flags: 100 * float(np.mean(flags))  # noqa: E731
    end = [a["truth_end_speed"] for a in after], [a["truth_end_spin"] for a in after]
    rest = {"truth_pct": share([t["truth_at_rest"] for t in tosses]), "truth_end_pct": share(at_rest(*end)),
            "model_pct": share([t["model_at_rest"] for t in tosses]), "truth_end_pct_x4": share(at_rest(*end, 4))}
    curves = {}
    for align, fn in (("end", align_end), ("start", align_start)):
        rows = {k: fn([t["series"][k] for t in tosses]) for k in tosses[0]["series"]}
        width = next(iter(rows.values())).shape[1]
        time = (np.arange(width) - width + 0.5) * step if align == "end" else (np.arange(width) + HISTORY - 0.5) * step
        curves[align] = {"time_s": time, **{k: band(v) for k, v in rows.items()}}
    past = {k: np.stack([a[k] for a in after]) for k in after[0] if k.startswith("model_")}
    curves["after"] = {"time_s": (np.arange(AFTER_STEPS) + 0.5) * step, **{k: band(v) for k, v in past.items()}}
    rests = {f: at_rest(past["model_speed"], past["model_spin"], f).mean(axis=0) * 100 for f in (1, 4)}
    after_rows = {str(k): {**{n: {q: float(b[q][k - 1]) for q in ("mean", "median", "q75")}
                              for n, b in curves["after"].items() if n != "time_s"},
                           "model_at_rest_pct": float(rests[1][k - 1]), "model_at_rest_pct_x4": float(rests[4][k - 1])}
                  for k in AFTER_ROWS if k <= AFTER_STEPS}
    truth_end = {k: band(np.array([[a[k]] for a in after])) for k in after[0] if k.startswith("truth_")}
    skip = int(np.ceil(JITTER_AFTER / step)) - HISTORY + 1   # the series start at step HISTORY - 1
    late = {k: np.concatenate([t["series"][k][skip:] for t in tosses]) for k in ("truth_speed", "truth_spin")}
    jitter = {"after_s": JITTER_AFTER, "steps": int(late["truth_speed"].size),
              "tosses": sum(len(t["series"]["truth_speed"]) > skip for t in tosses),
              **{f"{k}_{q}": float(np.percentile(v, q)) if v.size else None
                 for k, v in late.items() for q in (50, 99)}}
    return {"windows": table, "rest": rest, "curves": curves, "after_end": after_rows,
            "truth_end": {k: {q: float(v[q][0]) for q in ("mean", "median", "q75")} for k, v in truth_end.items()},
            "truth_jitter_at_rest": jitter}


def plot(path: Path, summary: dict, align: str = "end") -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    c, after, j = summary["curves"][align], summary["curves"]["after"], summary["truth_jitter_at_rest"]
    count = np.asarray(c["truth_speed"]["count"])   # the start plot ends where only one toss is left
    keep = slice(-PLOT_BEFORE, None) if align == "end" else slice(0, int(np.flatnonzero(count >= 2)[-1]) + 1)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label, limit in zip(axes, ("speed", "spin"), ("speed of the centre [m/s]", "spin [rad/s]"),
                                     (REST_SPEED, REST_SPIN)):
        parts = [("truth", "k", "truth (tracked cube)", c, keep), ("model", "C0", f"GNS {MODEL}", c, keep)]
        if align == "end":
            parts.append(("model", "C0", None, after, slice(0, PLOT_AFTER)))
            end = summary["truth_end"]
            ax.plot(end["truth_end_time_s"]["median"], end[f"truth_end_{key}"]["median"], "k*", ms=9,
                    label=f"truth over its last {summary['stride']} recorded frames: median")
        for who, colour, name, curve, sl in parts:
            b, t = curve[f"{who}_{key}"], np.asarray(curve["time_s"])[sl]
            ax.plot(t, np.asarray(b["median"])[sl], color=colour, marker="o", ms=3,
                    ls="-" if name else "--", label=name and f"{name}: median, quartiles")
            ax.plot(t, np.asarray(b["mean"])[sl], color=colour, lw=0.8, ls=":", label=name and f"{name}: mean")
            ax.fill_between(t, np.asarray(b["q25"])[sl], np.asarray(b["q75"])[sl], color=colour, alpha=0.18, lw=0)
        ax.axhline(limit, color="C3", lw=0.8, ls="--", label=f"at rest: below {REST_SPEED} m/s and {REST_SPIN} rad/s")
        if j[f"truth_{key}_99"] is not None:
            ax.axhspan(1e-5, j[f"truth_{key}_99"], color="k", alpha=0.08,
                       label=f"truth at rest: tracking jitter (99th pct, {j['tosses']} long tosses)")
        if align == "end":
            ax.axvspan(-WINDOW / summary["frame_rate"], 0, color="C3", alpha=0.06, label=f"last {WINDOW} frames")
            ax.axvline(0, color="k", lw=0.6)
        else:
            ax.axvline(c["time_s"][int(np.argmax(count < 10))], color="k", ls=":", lw=0.8,
                       label="fewer than 10 tosses on")
        ax.set_yscale("log")
        ax.set_ylim(1e-4 if key == "speed" else 1e-3, None)
        ax.set_ylabel(label)
        ax.set_xlabel("time from the last frame the model reaches in the toss [s]" if align == "end" else
                      "time from the first recorded frame [s]")
        ax.grid(alpha=0.3, which="both", lw=0.4)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="lower center", ncol=4, fontsize=7)
    note = "; the recording ends 0-7 frames after the model's last frame, the cube stopped; dashed: the model rolled on"
    fig.suptitle(f"Coming to rest: {summary['num_tosses']} held-out real cube tosses, aligned at the {align} of "
                 f"each ({int(count[keep].min())}-{int(count[keep].max())} tosses a point, each one 54 ms model "
                 f"step){note if align == 'end' else ''}", fontsize=9, wrap=True)
    fig.tight_layout(rect=(0, 0.13, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


_plain = lambda v: v.item() if hasattr(v, "item") else v  # noqa: E731


def _fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}g}" if abs(v) < 1 else f"{v:.{digits - 1}f}"


def table_lines(summary: dict) -> list[str]:
    lines = ["| window (recorded frames) | model steps | speed m/s: model / truth | ratio | spin rad/s: model / "
             "truth | ratio | position % | rotation deg |", "|---|---|---|---|---|---|---|---|"]
    for name, w in summary["windows"].items():
        lines.append(f"| {name} | {'-'.join(map(str, sorted(set(w['steps']))))} | {_fmt(w['model_speed'], 3)} / "
                     f"{_fmt(w['truth_speed'], 3)} | {_fmt(w['speed_ratio'])} | {_fmt(w['model_spin'], 3)} / "
                     f"{_fmt(w['truth_spin'], 3)} | {_fmt(w['spin_ratio'])} | {w['position_error_pct']:.1f} | "
                     f"{w['rotation_error_deg']:.1f} |")
    return lines


def after_lines(summary: dict) -> list[str]:
    step, t, r = summary["stride"] / summary["frame_rate"], summary["truth_end"], summary["rest"]
    cell = lambda d, k, a="mean": f"{_fmt(d[k]['median'])} ({_fmt(d[k][a])})"  # noqa: E731
    lines = ["| | speed m/s: median (mean) | spin rad/s: median (mean) | at rest (at 4x) | moved since: mm, median "
             "(75th pct) | turned since: deg, median (75th pct) |", "|---|---|---|---|---|---|",
             f"| truth, its last {summary['stride']} recorded frames | {cell(t, 'truth_end_speed')} | "
             f"{cell(t, 'truth_end_spin')} | {r['truth_end_pct']:.0f}% ({r['truth_end_pct_x4']:.0f}%) | "
             f"{cell(t, 'truth_slid_mm', 'q75')} to its end | {cell(t, 'truth_turned_deg', 'q75')} to its end |"]
    for k, a in summary["after_end"].items():
        lines.append(f"| model, step +{k} ({int(k) * step:.2f} s) | {cell(a, 'model_speed')} | {cell(a, 'model_spin')} "
                     f"| {a['model_at_rest_pct']:.0f}% ({a['model_at_rest_pct_x4']:.0f}%) | "
                     f"{cell(a, 'model_slid_mm', 'q75')} | {cell(a, 'model_turned_deg', 'q75')} |")
    return lines


def report(out: Path, summary: dict) -> Path:
    r, j, s = summary["rest"], summary["truth_jitter_at_rest"], summary["stride"]
    lines = [f"# Coming to rest: `{MODEL}` on the {summary['num_tosses']} test tosses of its recipe", "",
             f"Made by `{summary['command']}` (test data `{summary['test_data']}`, the recipe's split: training data "
             f"fingerprint {summary['recipe_fingerprint'][:16]}). Rolled out as `gns eval --run {MODEL} --data "
             f"{summary['test_data']} --at-data-rate` does: {summary['whole']['position_error_pct']:.2f}% / "
             f"{summary['whole']['rotation_error_deg']:.2f} deg over all frames.", "",
             f"Speed and spin over each model step ({s} recorded frames, {1000 * s / summary['frame_rate']:.0f} ms), "
             "model and truth read at the same frames; the mean over tosses of each toss's mean over the window; "
             f"ratio = model / truth; errors at every recorded frame of the window. {WINDOW} frames hold "
             f"{WINDOW // s} whole model steps, {LAST} frames one.", "", *table_lines(summary), "",
             f"At rest over the last model step of the toss (speed < {REST_SPEED} m/s and spin < {REST_SPIN} rad/s): "
             f"the truth in {r['truth_pct']:.0f}% of the tosses, the model in {r['model_pct']:.0f}%. The recording "
             f"goes on 0-7 frames past that step; over its own last {s} frames the truth is at rest in "
             f"{r['truth_end_pct']:.0f}% ({r['truth_end_pct_x4']:.0f}% at 4 times the thresholds).", "",
             f"Past the end: the model rolled out {AFTER_STEPS} steps further from the same start, the real cube "
             f"having stopped (moved since: from the last frame the model reaches in the toss).", "",
             *after_lines(summary), "",
             f"The truth's jitter at rest (its steps from {j['after_s']} s after release on, {j['steps']} steps of "
             f"{j['tosses']} tosses): median {_fmt(j['truth_speed_50'])} m/s and {_fmt(j['truth_spin_50'])} rad/s, "
             f"99th percentile {_fmt(j['truth_speed_99'])} m/s and {_fmt(j['truth_spin_99'])} rad/s.", "",
             "![speed and spin at the end of the toss](rest.png)", "", "![from the start](rest_start.png)"]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    return _plain(v)


def extended_rollout(test: Path, steps: int) -> tuple[list[tuple], list, list[int]]:
    """The model's own-rate tracks of the test tosses rolled out `steps` past each one's end, the
    recorded tosses, and the index of each one's last in-toss step."""
    sim, saved = load_simulator(MODEL, options=default_options(MODEL))
    ds, scenes = load_split(test, "test", None, ModelSpec.from_dict(saved["spec"]).frame_rate)
    recorded = Dataset(test).load("test")
    padded = []
    for sc, rec in zip(scenes, recorded, strict=True):
        hold = lambda a, last: np.concatenate([a, np.repeat(last[None], steps, axis=0)])  # noqa: E731
        padded.append(dataclasses.replace(sc, positions=hold(sc.positions, rec.positions[-1]),
                                          quaternions=hold(sc.quaternions, rec.quaternions[-1]),
                                          velocities=hold(sc.velocities, 0 * sc.velocities[-1]),
                                          angular_velocities=hold(sc.angular_velocities, 0 * sc.velocities[-1])))
    pred = rollout_scenes(sim, padded, ds.meshes, ds.frame_rate, progress=False)
    return [(p.positions[:, 0], p.quaternions[:, 0]) for p in pred], recorded, [sc.num_frames - 1 for sc in scenes]


def run(src: Path, out: Path, figure: Path | None = None, command: str = "") -> dict:
    recipe = load_recipe(MODEL)
    ds, test = data_stage_of(recipe, out, None, Path(src), 1)
    want = recipe.data["fingerprint"]
    if ds.fingerprint != want:
        raise DataError(f"{src}: the recipe's split of these tosses is not the one {MODEL} was trained on (training "
                        f"data fingerprint {ds.fingerprint[:16]}, the recipe's {want[:16]}): its test tosses may "
                        "not be held out")
    say(f"rolling out {MODEL} on {test}")
    results, pred, truth, full = evaluate_run(MODEL, test, "test", at_data_rate=True, progress=False)
    if results["trained_on_fingerprint"] not in (None, want) or results["num_diverged"]:
        raise DataError(f"{MODEL}: trained on data {str(results['trained_on_fingerprint'])[:16]}, not the recipe's, "
                        f"or {results['num_diverged']} rollouts diverged")
    stride, rate = int(results["model_stride"]), float(full.frame_rate)
    errors = scene_errors(pred, truth, full.meshes, float(full.floor["z"]) if full.floor else 0.0)
    tosses = measure(pred, truth, errors, stride, rate)
    say(f"rolling out {AFTER_STEPS} steps past the end of each toss")
    tracks, recorded, last = extended_rollout(test, AFTER_STEPS)
    # recorded, since the past-the-end figures are only the scored rollout if padding changed nothing before it
    same = max(float(np.abs(tr[0][:n + 1] - p.positions[::stride, 0]).max()) for tr, n, p in zip(tracks, last, pred))
    after = [after_end(tr, rec, n, stride, rate) for tr, rec, n in zip(tracks, recorded, last)]
    summary = {**summarise(tosses, after, stride, rate), "stride": stride, "frame_rate": rate,
               "num_tosses": len(tosses), "test_data": str(test), "recipe_fingerprint": want,
               "test_fingerprint": results["data_fingerprint"], "command": command,
               "rest_thresholds": {"speed_m_s": REST_SPEED, "spin_rad_s": REST_SPIN},
               "whole": {k: results[k] for k in ("position_error_pct", "rotation_error_deg", "penetration_pct")},
               "rollout_options": results["rollout_options"], "extended_rollout_max_difference": same,
               "tosses": [{k: v for k, v in t.items() if k != "series"} for t in tosses]}
    write_json(out / "results.json", _jsonable(summary))
    plot(out / "rest.png", summary, "end")
    plot(out / "rest_start.png", summary, "start")
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "rest.png", figure)
    report(out, summary)
    say(f"report: {out / 'report.md'}")
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.real_cubes_rest", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, required=True, help="ContactNets data folder (tosses_processed/N.pt)")
    ap.add_argument("--out", type=Path, default=Path("runs/real_cubes_rest"), help="output folder")
    ap.add_argument("--figure", type=Path, help="also write the end-aligned figure here")
    a = ap.parse_args(argv)
    command = f"python -m pipelines.real_cubes_rest --src PATH/TO/contact-nets/data --out {a.out}"
    return guarded(lambda: run(a.src, a.out, a.figure, command))


if __name__ == "__main__":
    sys.exit(main())
