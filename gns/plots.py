"""Figures and animations of rollouts: PNG and GIF files, no screen needed.

Figures are built with matplotlib's object API (`Figure` + the Agg canvas), not pyplot: nothing
global is touched (no backend switch, no figure registry that grows when a script draws
hundreds of plots), so this works on a headless machine and inside other programs.

Inputs are `datagen.shards.Scene` objects (predicted and true, same frames) and the dataset's
rest meshes {shape: (vertices (V, 3), faces (F, 3))}. Every function writes `path` (creating
its folder) and returns it as a Path.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.animation import PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
from scipy.spatial import ConvexHull, QhullError

from datagen.shards import Dataset
from gns.network import HISTORY
from gns.geometry import pose_to_vertices
from gns.metrics import object_width, per_frame_curves, scene_errors

PRED_COLOR = "tab:blue"
TRUE_COLOR = "black"
CONTACT_COLOR = "tab:red"
METRIC_LABELS = {
    "position_error_pct": "position error [% of width]",
    "rotation_error_deg": "rotation error [deg]",
    "penetration_pct": "penetration [% of width]",
}


def new_figure(figsize) -> Figure:
    """A figure on its own Agg canvas, outside pyplot's registry (see the module doc)."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path, dpi: int) -> Path:
    """Write `fig` to `path`, creating its folder; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def _vertices(scene, meshes, obj: int) -> np.ndarray:
    """World vertices of object obj over time: (T, V, 3)."""
    rest = meshes[scene.shape[obj]][0]
    return pose_to_vertices(scene.positions[:, obj], scene.quaternions[:, obj], scene.scale[obj], rest)


def _main_horizontal_direction(xy: np.ndarray) -> np.ndarray:
    """Unit (2,) direction of largest horizontal motion of a (T, 2) path (principal axis),
    pointing from the start towards the end; x if the path does not move."""
    d = xy - xy.mean(axis=0)
    if np.abs(d).max() < 1e-12:
        return np.array([1.0, 0.0])
    u = np.linalg.svd(d, full_matrices=False)[2][0]
    return -u if np.dot(xy[-1] - xy[0], u) < 0 else u


def _outline(points2d: np.ndarray) -> np.ndarray:
    """Closed outline (K+1, 2) of the projection of a convex body given its projected vertices."""
    try:
        hull = points2d[ConvexHull(points2d).vertices]
    except QhullError:  # degenerate projection (e.g. a flat mesh seen edge-on)
        hull = points2d
    return np.vstack([hull, hull[:1]])


def contact_frames(scene, meshes, obj: int = 0, floor_z: float = 0.0, tol: float | None = None) -> np.ndarray:
    """Indices of the frames where object obj's lowest vertex is within tol of the floor (or
    below it). tol defaults to 2% of the object's width."""
    verts = _vertices(scene, meshes, obj)
    if tol is None:
        tol = 0.02 * float(object_width(scene.scale[obj], meshes[scene.shape[obj]][0]))
    return np.nonzero(verts[..., 2].min(axis=1) - floor_z <= tol)[0]


def feature_edges(faces: np.ndarray, vertices: np.ndarray, angle_deg: float = 1.0) -> np.ndarray:
    """(E, 2) vertex pairs of a triangle mesh's edges, dropping edges between coplanar triangles.

    The triangulation diagonals of a flat face are not edges of the solid; drawing them clutters
    plots of a cube. Boundary edges (one triangle) are kept.
    """
    faces = np.asarray(faces, np.int64)
    v = np.asarray(vertices, np.float64)
    normals = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    edges = np.sort(edges, axis=1)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    uniq, start, counts = np.unique(edges, axis=0, return_index=True, return_counts=True)
    keep = np.ones(len(uniq), bool)
    two = counts == 2
    cos = np.sum(normals[owner[start[two]]] * normals[owner[start[two] + 1]], axis=1)
    keep[two] = cos < np.cos(np.radians(angle_deg))
    return uniq[keep]


def plot_trajectory(pred, true, meshes: Mapping[str, tuple], path, obj: int = 0, dt: float | None = None,
                    floor_z: float = 0.0, contact_tol: float | None = None, num_outlines: int = 6,
                    unit: str = "", title: str | None = None, dpi: int = 120) -> Path:
    """The paper's Figure 1 view of one object: predicted vs true.

    (a) the centre's path in the vertical plane through the direction of largest horizontal
        motion of the truth, with the object's outline at num_outlines frames;
    (b) vertical velocity (finite difference of the centre height) against time, with the true
        contact frames (lowest vertex within contact_tol of the floor) as red vertical lines.
    dt: seconds per frame (time axis in s, velocity per s); None plots per frame.
    unit: the length unit for axis labels ("m", "half-widths", ...).
    """
    u2 = _main_horizontal_direction(true.positions[:, obj, :2])
    u = np.array([u2[0], u2[1], 0.0])
    origin = true.positions[0, obj]
    lu = f" [{unit}]" if unit else ""

    fig = new_figure((11, 4.2))
    ax_a, ax_b = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.3, 1]})
    T = true.num_frames
    shown = np.unique(np.linspace(0, T - 1, max(num_outlines, 1)).round().astype(int))
    for scene, color, label, ls in ((true, TRUE_COLOR, "truth", "-"), (pred, PRED_COLOR, "prediction", "--")):
        p = scene.positions[:, obj] - origin
        s, z = p @ u, scene.positions[:, obj, 2]
        ax_a.plot(s, z, ls, color=color, lw=1.5, label=f"{label} (centre)")
        verts = _vertices(scene, meshes, obj)[shown]                     # (K, V, 3)
        last_label = None
        for k, t in enumerate(shown):
            outline = _outline(np.column_stack([(verts[k] - origin) @ u, verts[k][:, 2]]))
            ax_a.plot(outline[:, 0], outline[:, 1], ls, color=color, lw=0.8, alpha=0.6)
            # Frame numbers on the truth, skipped where they would print over the previous one.
            width = np.ptp(outline[:, 0])
            if scene is true and (last_label is None or np.hypot(s[t] - last_label[0], z[t] - last_label[1]) > 0.3 * width):
                ax_a.annotate(str(t), (s[t], z[t]), fontsize=7, color="dimgray", ha="center", va="center",
                              bbox=dict(fc="white", ec="none", alpha=0.7, pad=0.5))
                last_label = (s[t], z[t])
    ax_a.axhline(floor_z, color="gray", lw=1)
    ax_a.set_aspect("equal", adjustable="datalim")
    ax_a.set_xlabel(f"horizontal position along ({u2[0]:+.2f}, {u2[1]:+.2f}){lu}")
    ax_a.set_ylabel(f"height z{lu}")
    ax_a.set_title("(a) centre path and outlines (numbers: frame)", fontsize=10)
    ax_a.legend(fontsize=8, loc="upper right")

    step = dt if dt else 1.0
    t_mid = (np.arange(T - 1) + 0.5) * step                              # finite difference at midpoints
    for scene, color, label, ls in ((true, TRUE_COLOR, "truth", "-"), (pred, PRED_COLOR, "prediction", "--")):
        vz = np.diff(scene.positions[:, obj, 2]) / step
        ax_b.plot(t_mid, vz, ls, color=color, lw=1.3, label=label)
    for k, t in enumerate(contact_frames(true, meshes, obj, floor_z, contact_tol)):
        ax_b.axvline(t * step, color=CONTACT_COLOR, lw=0.8, alpha=0.35, label="true contact" if k == 0 else None)
    ax_b.axhline(0.0, color="gray", lw=0.6)
    ax_b.set_xlabel("time [s]" if dt else "frame")
    ax_b.set_ylabel(f"vertical velocity [{unit or 'length'}/{'s' if dt else 'frame'}]")
    ax_b.set_title("(b) vertical velocity", fontsize=10)
    ax_b.legend(fontsize=8)
    name = true.attrs.get("toss_id", true.attrs.get("scene_id", ""))
    fig.suptitle(title or f"scene {name}, object {obj}: prediction vs truth")
    fig.tight_layout()
    return save_figure(fig, path, dpi)


def _as_models(per_frame_errors: Mapping) -> dict[str, dict[str, np.ndarray]]:
    """{metric: array} (one model) or {label: {metric: array}} -> {label: {metric: (T,)}};
    (T, N) arrays are averaged over objects."""
    if all(isinstance(v, Mapping) for v in per_frame_errors.values()):
        models = per_frame_errors
    else:
        models = {"model": per_frame_errors}
    out = {}
    for label, errs in models.items():
        out[label] = {}
        for k, v in errs.items():
            v = np.asarray(v, np.float64)
            out[label][k] = v.reshape(v.shape[0], -1).mean(axis=1) if v.ndim > 1 else v
    return out


def plot_error_vs_time(per_frame_errors: Mapping, path, dt: float | None = None, num_given: int = HISTORY,
                       title: str | None = None, dpi: int = 120) -> Path:
    """Error against frame: one panel per metric present (position %, rotation degrees,
    penetration %), one line per model.

    per_frame_errors: {metric: (T,) or (T, N)} for one model, or {label: {metric: ...}} for
    several (e.g. gns.metrics.per_frame_curves per model). A "true_penetration_pct" entry is
    drawn dashed in the penetration panel as the ground truth's floor. The first num_given
    frames (copied from the truth) are shaded.
    """
    models = _as_models(per_frame_errors)
    metrics = [m for m in METRIC_LABELS if any(m in e for e in models.values())]
    if not metrics:
        raise ValueError(f"no known metric among {sorted({k for e in models.values() for k in e})}")
    fig = new_figure((4.2 * len(metrics), 3.6))
    axes = np.atleast_1d(fig.subplots(1, len(metrics)))
    step = dt if dt else 1.0
    for ax, m in zip(axes, metrics):
        for i, (label, errs) in enumerate(models.items()):
            if m in errs:
                t = np.arange(len(errs[m])) * step
                ax.plot(t, errs[m], color=f"C{i}", lw=1.4, label=label)
            if m == "penetration_pct" and "true_penetration_pct" in errs and i == 0:
                tp = errs["true_penetration_pct"]
                ax.plot(np.arange(len(tp)) * step, tp, "--", color="gray", lw=1, label="ground truth")
        if num_given > 0:
            ax.axvspan(0, (num_given - 1) * step, color="gray", alpha=0.15, lw=0)
        ax.set_xlabel("time [s]" if dt else "frame")
        ax.set_ylabel(METRIC_LABELS[m])
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title or "rollout error against time (shaded: given frames)")
    fig.tight_layout()
    return save_figure(fig, path, dpi)


def _axis_limits(true_verts: list[np.ndarray], pred_verts: list[np.ndarray], floor_z: float):
    """Fixed (3, 2) limits: the truth's extent, widened to include the prediction but by at most
    one truth span per side, so a prediction that flies away does not shrink the picture."""
    t = np.concatenate([v.reshape(-1, 3) for v in true_verts])
    lo, hi = t.min(axis=0), t.max(axis=0)
    span = np.maximum(hi - lo, 1e-6)
    p = np.concatenate([v.reshape(-1, 3) for v in pred_verts])
    p = p[np.isfinite(p).all(axis=1)]
    if len(p):
        lo = np.minimum(lo, np.maximum(p.min(axis=0), lo - span))
        hi = np.maximum(hi, np.minimum(p.max(axis=0), hi + span))
    lo[2] = min(lo[2], floor_z)
    pad = 0.05 * (hi - lo).max()
    return np.stack([lo - pad, hi + pad], axis=1)


def animate_rollout(pred, true, meshes: Mapping[str, tuple], path, fps: float = 12, floor_z: float = 0.0,
                    stride: int = 1, max_frames: int | None = None, dpi: int = 80,
                    labels: Sequence[str] = ("prediction", "truth")) -> Path:
    """GIF of the rollout (left) beside the truth (right): mesh edges of every object per frame
    above the floor, with the same fixed axes on both sides.

    stride: draw every stride-th frame; max_frames: stop after that many drawn frames. The GIF
    has len(range(0, T, stride)[:max_frames]) frames; each shows its frame number.
    """
    edges = {name: feature_edges(m[1], m[0]) for name, m in meshes.items()}
    scenes = (pred, true)
    verts = [[_vertices(sc, meshes, n) for n in range(sc.num_objects)] for sc in scenes]   # [scene][obj] (T, V, 3)
    lim = _axis_limits(verts[1], verts[0], floor_z)
    frames = list(range(0, true.num_frames, max(1, stride)))[:max_frames]
    if not frames:
        raise ValueError("no frames to animate (max_frames < 1?)")

    fig = new_figure((8, 4.2))
    collections = []
    for k, (sc, label) in enumerate(zip(scenes, labels)):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.set_xlim(*lim[0]), ax.set_ylim(*lim[1]), ax.set_zlim(*lim[2])
        ax.set_box_aspect(tuple(lim[:, 1] - lim[:, 0]))
        ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z")
        ax.tick_params(labelsize=6)
        ax.set_title(label, fontsize=10)
        x0, x1, y0, y1 = *lim[0], *lim[1]
        ax.add_collection3d(Poly3DCollection([[(x0, y0, floor_z), (x1, y0, floor_z), (x1, y1, floor_z),
                                               (x0, y1, floor_z)]], facecolor="gray", alpha=0.2), autolim=False)
        color = PRED_COLOR if k == 0 else TRUE_COLOR
        per_obj = []
        for n in range(sc.num_objects):
            lc = Line3DCollection(verts[k][n][frames[0]][edges[sc.shape[n]]], colors=color, linewidths=1.0)
            ax.add_collection3d(lc, autolim=False)  # limits are fixed above
            per_obj.append(lc)
        collections.append(per_obj)
    stamp = fig.suptitle("")

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi):
        for t in frames:
            for k, sc in enumerate(scenes):
                for n in range(sc.num_objects):
                    v = verts[k][n][t]
                    collections[k][n].set_segments(v[edges[sc.shape[n]]])        # (E, 2, 3)
            # The changing stamp also keeps Pillow from merging identical frames (an object at rest).
            stamp.set_text(f"frame {t} / {true.num_frames - 1}")
            writer.grab_frame()
    return path


def _worst_first(per_scene: list[float]) -> list[int]:
    return list(np.argsort(per_scene)[::-1])


def write_plots(out: str | Path, pred: list, true: list, ds: Dataset, results: dict, count: int = 2,
                errors: list[dict] | None = None) -> list[Path]:
    """`gns eval --plots`: Figure-1 views and a GIF of the best and worst scenes, and error against time.
    `errors`: gns.metrics.scene_errors of pred against true, if already computed."""
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
