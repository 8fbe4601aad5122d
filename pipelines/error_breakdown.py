"""Where a model's rollout error sits: spread over scenes, and rotation against position.

    python -m pipelines.error_breakdown --run movi_a --data data/movi_a_4000 --free-flight --symmetrize \
        [--split test|train|valid] [--limit N] [--autocast bf16] [--json FILE]

Rolls out a split as `gns eval` does and prints three tables:
- scenes: mean and median of the per-scene errors, and the share of the total the worst 5%,
  10%, 20%, 50% of scenes hold (a few bad scenes, or error everywhere?);
- rotation by position error: object-frames binned by their position error (% of size), the
  mean rotation error of each bin and its share of all rotation error (is the rotation wrong
  on trajectories that are right?);
- rotation by true spin: the same binned by the true turn per frame;
- in scenes of several objects, by meeting: object-frames of objects that never come near another
  (their bounding spheres never touch in the truth, at a frame or between two), and of the others
  before and after their first meeting (is the error the contacts between objects', or what
  follows them?).
`--split train` on a model's own training scenes against `--split test` tells overfitting
from underfitting (experiments/log.md).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gns.evaluate import evaluate_run, write_json
from gns.metrics import bounding_gaps, scene_errors
from pipelines.common import guarded

POSITION_BINS = (0.0, 5.0, 10.0, 25.0, 50.0, np.inf)   # % of size
SPIN_BINS = (0.0, 1.0, 5.0, 15.0, np.inf)               # true degrees a frame
WORST = (0.05, 0.10, 0.20, 0.50)


def worst_shares(per_scene: np.ndarray) -> dict[str, float]:
    """The share of the summed error the worst q of scenes hold, for each q of WORST."""
    ordered = np.sort(per_scene)[::-1]
    total = ordered.sum()
    return {f"{q:.0%}": float(ordered[:max(1, int(round(q * len(ordered))))].sum() / total) if total > 0 else 0.0
            for q in WORST}


def binned(values: np.ndarray, by: np.ndarray, edges) -> list[dict]:
    """For each bin [lo, hi) of `by`: its share of the entries, the mean of `values` in it and
    its share of their sum."""
    total = values.sum()
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (by >= lo) & (by < hi)
        rows.append({"low": float(lo), "high": float(hi), "share_of_frames": float(m.mean()),
                     "mean": float(values[m].mean()) if m.any() else None,
                     "share_of_error": float(values[m].sum() / total) if total > 0 else 0.0})
    return rows


MEETING = ("never near another object", "before its first meeting", "from its first meeting on")


def swept_touch(sc, meshes: dict) -> np.ndarray:
    """(T, N) whether an object's bounding sphere may touch another's at frame t or on the way from
    t-1 to t: the gap between the two centres' straight paths, less half of the two moves (a path
    that bends within the frame, a bounce off the floor, strays from its chord by up to half its
    length). At 12 fps a thrown object covers half a size a frame, so two can meet and part
    between recorded frames; judged at the frames alone, such objects were counted as never
    meeting (experiments/log.md, 2026-12-07)."""
    gap = bounding_gaps(sc, meshes)                                   # (T, N, N) at the frames
    offset = sc.positions[:, :, None] - sc.positions[:, None]         # (T, N, N, 3) between centres
    reach = np.linalg.norm(offset, axis=-1) - gap                     # the two radii (inf on the diagonal)
    d0, step = offset[:-1], offset[1:] - offset[:-1]
    s = np.clip(-(d0 * step).sum(-1) / np.maximum((step * step).sum(-1), 1e-300), 0.0, 1.0)
    moved = np.linalg.norm(sc.positions[1:] - sc.positions[:-1], axis=-1)          # (T-1, N)
    between = np.linalg.norm(d0 + s[..., None] * step, axis=-1) - reach[1:] - (moved[:, :, None] + moved[:, None]) / 2
    return np.concatenate([gap[:1] < 0, (np.minimum(gap[1:], between) < 0)]).any(axis=2)


def meeting_labels(true_scenes: list, meshes: dict) -> list[np.ndarray]:
    """Per scene (T, N): 0 for an object whose bounding sphere never touches another's in the
    truth (at a frame or between two: swept_touch), else 1 before the first frame it does and
    2 from that frame on."""
    out = []
    for sc in true_scenes:
        near = swept_touch(sc, meshes)                                 # (T, N)
        first = np.where(near.any(axis=0), near.argmax(axis=0), sc.num_frames)
        label = np.where(np.arange(sc.num_frames)[:, None] >= first[None], 2, 1)
        out.append(np.where(near.any(axis=0)[None], label, 0))
    return out


def breakdown(errors: list[dict], labels: list[np.ndarray] | None = None) -> dict:
    """The tables from gns.metrics.scene_errors of a split (and, given meeting_labels, by meeting)."""
    pos = np.array([e["position_error_pct"].mean() for e in errors])
    rot = np.array([e["rotation_error_deg"].mean() for e in errors])
    p, r, s = (np.concatenate([e[k].ravel() for e in errors])
               for k in ("position_error_pct", "rotation_error_deg", "true_spin_deg"))
    return {"num_scenes": len(errors), "num_object_frames": int(p.size),
            "scenes": {"position_error_pct": {"mean": float(pos.mean()), "median": float(np.median(pos)),
                                              "worst_share": worst_shares(pos)},
                       "rotation_error_deg": {"mean": float(rot.mean()), "median": float(np.median(rot)),
                                              "worst_share": worst_shares(rot)}},
            "rotation_by_position_error": binned(r, p, POSITION_BINS),
            "rotation_by_true_spin": binned(r, s, SPIN_BINS),
            **({"by_meeting": by_meeting(errors, labels)} if labels and any(x.shape[1] > 1 for x in labels) else {})}


def by_meeting(errors: list[dict], labels: list[np.ndarray]) -> list[dict]:
    p, r = (np.concatenate([e[k].ravel() for e in errors]) for k in ("position_error_pct", "rotation_error_deg"))
    lab = np.concatenate([x.ravel() for x in labels])
    return [{"group": name, "share_of_frames": float((lab == k).mean()),
             "position_error_pct": float(p[lab == k].mean()) if (lab == k).any() else None,
             "rotation_error_deg": float(r[lab == k].mean()) if (lab == k).any() else None,
             "share_of_position_error": float(p[lab == k].sum() / p.sum()) if p.sum() > 0 else 0.0}
            for k, name in enumerate(MEETING)]


def format_breakdown(b: dict) -> str:
    lines = [f"{b['num_scenes']} scenes, {b['num_object_frames']} object-frames", "",
             "per scene          mean   median   worst 5% / 10% / 20% / 50% of scenes hold"]
    for key, label in (("position_error_pct", "position %"), ("rotation_error_deg", "rotation deg")):
        d = b["scenes"][key]
        shares = " / ".join(f"{v:.0%}" for v in d["worst_share"].values())
        lines.append(f"{label:<16} {d['mean']:6.2f}  {d['median']:6.2f}   {shares}")
    for key, label, unit in (("rotation_by_position_error", "position error", "%"),
                             ("rotation_by_true_spin", "true spin", " deg/frame")):
        lines += ["", f"{label + ' bin':<24} object-frames   mean rotation deg   share of rotation error"]
        for row in b[key]:
            hi = "inf" if np.isinf(row["high"]) else f"{row['high']:g}"
            mean = "-" if row["mean"] is None else f"{row['mean']:.1f}"
            edges = f"{row['low']:g}-{hi}{unit}"
            lines.append(f"{edges:<24} {row['share_of_frames']:>13.0%}   {mean:>17}   {row['share_of_error']:>23.0%}")
    if "by_meeting" in b:
        lines += ["", f"{'object-frames':<28} share   position %   rotation deg   share of position error"]
        for row in b["by_meeting"]:
            pos, rot = (("-" if row[k] is None else f"{row[k]:.1f}") for k in ("position_error_pct", "rotation_error_deg"))
            lines.append(f"{row['group']:<28} {row['share_of_frames']:>5.0%}   {pos:>10}   {rot:>12}   "
                         f"{row['share_of_position_error']:>23.0%}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.error_breakdown", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="run folder, checkpoint or shipped model name")
    ap.add_argument("--data", required=True, type=Path, help="dataset folder")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, help="only the first N scenes")
    ap.add_argument("--free-flight", action="store_true", help="as gns eval --free-flight")
    ap.add_argument("--symmetrize", action="store_true", help="as gns eval --symmetrize (d2)")
    ap.add_argument("--keep-apart", action="store_true", help="as gns eval --keep-apart")
    ap.add_argument("--autocast", choices=("none", "bf16", "auto"), default="none")
    ap.add_argument("--json", type=Path, help="also write the tables as JSON")
    a = ap.parse_args(argv)

    def stages():
        _, pred, true, ds = evaluate_run(a.run, a.data, a.split, a.limit, progress=False, symmetrize=a.symmetrize,
                                         free_flight=a.free_flight, autocast=a.autocast,
                                         **({"keep_apart": True} if a.keep_apart else {}))
        b = breakdown(scene_errors(pred, true, ds.meshes), meeting_labels(true, ds.meshes))
        b.update(run=str(a.run), data=str(a.data), split=a.split, free_flight=a.free_flight, symmetrize=a.symmetrize)
        print(format_breakdown(b))
        if a.json:
            write_json(a.json, b)
    return guarded(stages)


if __name__ == "__main__":
    raise SystemExit(main())
