"""The cases of the 45-degree test and how a model is scored on them (pipelines.diagnostic_45).

A case is a shape, a size and a start: released at rest standing on its edge, or dropped onto the
edge from 0.5 or 1 size above the floor (the lowest vertex that high, at rest). Each case is 8
angles, 45 -+ {2, 1, 0.5, 0.25} degrees. A model is scored on a case through three inputs:

  data      PyBullet's first 3 frames of the drop (what `gns eval` and `gns rollout` read)
  api       gns.load(...).rollout from the release pose, as the Python API's docs say: for the
            edge, history= the pose held still (an object in contact); for a drop, velocities 0
            (the default: the three input frames by free flight backwards)
  api held  the drops through the API with history= the pose held still too (released from a
            hand at rest); the edge's is `api`

and each rolled out at every rollout variant asked for (VARIANTS: none and d1 by default). The
truth is PyBullet's side of each angle; a rollout is right where it lands on that side.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from datagen.tilted import side

ANGLES = (43.0, 44.0, 44.5, 44.75, 45.25, 45.5, 46.0, 47.0)
SHAPES = ("cube", "beveled_cube")
SIZES = ("small", "large")
STARTS = (("edge", 0.0), ("drop 0.5", 0.5), ("drop 1", 1.0))   # (name, lowest vertex above the floor, in sizes)
# rollout variants: (symmetrize, body_frames); none and d1 are one and two network calls a step
VARIANTS = {"none": ("none", False), "d1": ("d1", False), "d2": ("d2", False), "body frames": ("d2", True)}
DEFAULT_VARIANTS = ("none", "d1")
PATHS = ("data", "api", "api held")


def cases(shapes=SHAPES) -> list[dict]:
    """Every case of these shapes: {shape, size, start, height (in sizes)}, scenes case after case."""
    return [{"shape": sh, "size": si, "start": st, "height": h} for sh in shapes for si in SIZES for st, h in STARTS]


def sides(pred: list, true: list, angles) -> dict:
    """Per angle: PyBullet's side, the GNS's, agreement; and the mirrored pairs' check."""
    rows = []
    for a, p, t in zip(angles, pred, true, strict=True):
        s = float(t.scale[0])
        rows.append({"angle": a, "pybullet": side(t.positions, s), "gns": side(p.positions, s),
                     "pybullet_final_x": float(t.positions[-1, 0, 0]), "gns_final_x": float(p.positions[-1, 0, 0])})
        rows[-1]["agree"] = rows[-1]["pybullet"] == rows[-1]["gns"] != 0
    by_angle = {r["angle"]: r for r in rows}
    pairs = []
    for a in angles:
        b = 90.0 - a
        if a < 45 and b in by_angle:
            lo, hi = by_angle[a], by_angle[b]
            pairs.append({"d": 45.0 - a, "angles": [a, b],
                          "pybullet_mirrored": lo["pybullet"] == -hi["pybullet"] != 0,
                          "gns_mirrored": lo["gns"] == -hi["gns"] != 0})
    return {"rows": rows, "pairs": pairs, "agree": sum(r["agree"] for r in rows), "total": len(rows)}


class _Track:
    """A predicted centre track (frames, 1, 3) where `sides` reads one."""

    def __init__(self, positions: np.ndarray):
        self.positions = positions
        self.num_frames = len(positions)


def api_rollouts(model, true: list, held: bool) -> list[_Track]:
    """The API's rollouts of one case's scenes (one scene each, batched) from the release pose
    (frame 0 of the truth), to the truth's last frame: with `held` from history= the pose held
    still, else from velocities 0 (free flight backwards)."""
    pos = np.stack([t.positions[0, 0] for t in true])
    quat = np.stack([t.quaternions[0, 0] for t in true])
    history = (np.stack([pos, pos]), np.stack([quat, quat])) if held else None
    with warnings.catch_warnings():   # the ranges, outside training for a drop from rest: gns eval's list says it once
        warnings.simplefilter("ignore")
        out = model.rollout([t.shape[0] for t in true], pos, quat, history=history,
                            scales=[float(t.scale[0]) for t in true], friction=[float(t.friction[0]) for t in true],
                            restitution=[float(t.restitution[0]) for t in true], scene=list(range(len(true))),
                            steps=true[0].num_frames - 1)
    p = out.positions.detach().cpu().numpy()
    return [_Track(p[:, k:k + 1]) for k in range(len(true))]


def score(ckpt: Path, drops, case_list: list[dict], variants, say) -> tuple[dict, dict]:
    """{path: {variant: [per case: sides table]}} through every input path and variant, and the
    data path's predictions {variant: [scenes]} (for the plots)."""
    import gns
    from gns.evaluate import evaluate_run
    n = len(ANGLES)
    out: dict = {p: {} for p in PATHS}
    predicted, outside = {}, []
    for v in variants:
        sym, body = VARIANTS[v]
        say(f"eval: {v}: the drops from PyBullet's first 3 frames (gns eval)")
        res, pred, true, _ = evaluate_run(ckpt, drops.root, "test", symmetrize=sym, body_frames=body, progress=False)
        outside = res["outside_training"]
        by_index = {t.attrs["index"]: (p, t) for p, t in zip(pred, true, strict=True)}
        truth = drops.load("test")
        # a diverged rollout (left out by gns eval) lands on no side
        pairs = [by_index.get(i, (_Track(np.full((1, 1, 3), np.nan)), truth[i])) for i in range(len(truth))]
        predicted[v] = [p for p, _ in pairs]
        out["data"][v] = [sides([p for p, _ in pairs[k * n:(k + 1) * n]], truth[k * n:(k + 1) * n], ANGLES)
                          for k in range(len(case_list))]
        model = gns.load(ckpt, symmetrize=sym, body_frames=body, meshes=drops.meshes)
        say(f"eval: {v}: the drops through the Python API")
        for path, held in (("api", None), ("api held", True)):
            tables = []
            for k, case in enumerate(case_list):
                scenes = truth[k * n:(k + 1) * n]
                if path == "api held" and case["start"] == "edge":
                    tables.append(None)    # the edge is held in `api` already
                    continue
                tables.append(sides(api_rollouts(model, scenes, case["start"] == "edge" if held is None else held),
                                    scenes, ANGLES))
            out[path][v] = tables
    return {"paths": out, "outside_training": outside}, predicted


def totals(results: dict) -> dict:
    """{path: {variant: [right, scored]}} over every case."""
    out = {}
    for path, by_variant in results["paths"].items():
        out[path] = {v: [sum(t["agree"] for t in tables if t), sum(t["total"] for t in tables if t)]
                     for v, tables in by_variant.items()}
    return out


def _label(path: str, v: str) -> str:
    return {"data": "data", "api": "API", "api held": "API held"}[path] + f" {v}"


def table_lines(results: dict) -> list[str]:
    """The markdown table: a row a case, a column a path and variant, right sides of 8."""
    variants = list(results["paths"]["data"])
    cols = [(p, v) for p in PATHS for v in variants]
    lines = ["| shape | size | start | " + " | ".join(_label(p, v) for p, v in cols) + " |",
             "|---|---|---|" + "---|" * len(cols)]
    for k, case in enumerate(results["cases"]):
        cells = []
        for p, v in cols:
            t = results["paths"][p][v][k]
            cells.append("-" if t is None else f"{t['agree']}/{t['total']}")
        lines.append(f"| {case['shape']} | {case['size']} ({case['scale']:g}) | {case['start']} | " + " | ".join(cells) + " |")
    tot = totals(results)
    lines.append("| **all** | | | " + " | ".join(f"**{tot[p][v][0]}/{tot[p][v][1]}**" for p, v in cols) + " |")
    return lines


def wrong_lines(results: dict) -> list[str]:
    """One line per case and input with an angle on the wrong side: which angles, which side."""
    lines = []
    for p in PATHS:
        for v, tables in results["paths"][p].items():
            for case, t in zip(results["cases"], tables):
                if t is None:
                    continue
                bad = [f"{r['angle']:g} ({r['gns']:+d})" for r in t["rows"] if not r["agree"]]
                if bad:
                    lines.append(f"- {case['shape']} {case['size']} {case['start']}, {_label(p, v)}: " + ", ".join(bad))
    return lines or ["- none: every angle of every case on PyBullet's side"]


def plot(path: Path, panels: list[tuple[str, list, list]], dt: float, columns: int = 2) -> Path:
    """Fig. 3 as time series, a panel a case: centre x / size against time, PyBullet solid,
    GNS dashed, an angle a colour. panels: (title, predicted scenes, true scenes)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    rows = -(-len(panels) // columns)
    fig = Figure(figsize=(5.0 * columns, 3.6 * rows))
    FigureCanvasAgg(fig)
    cmap = colormaps["coolwarm"]
    for k, (title, pred, true) in enumerate(panels):
        ax = fig.add_subplot(rows, columns, k + 1)
        for i, (a, p, t) in enumerate(zip(ANGLES, pred, true)):
            c = cmap(i / max(len(ANGLES) - 1, 1))
            s = float(t.scale[0])
            ax.plot(np.arange(t.num_frames) * dt, t.positions[:, 0, 0] / s, color=c, lw=1.4, label=f"{a:g} deg")
            ax.plot(np.arange(p.num_frames) * dt, p.positions[:, 0, 0] / s, color=c, lw=1.4, ls="--")
        ax.axhline(0, color="gray", lw=0.6)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("centre x from the edge [sizes]")
        ax.set_title(f"{title}: PyBullet solid, GNS dashed", fontsize=8)
        if k == 0:
            ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path
