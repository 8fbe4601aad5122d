"""Rollout metrics in the ContactNets convention (used by Allen et al., CoRL 2022).

For a predicted and a true trajectory of object poses:
- position error: |p_pred - p_true| of the object centre, % of the object's width;
- rotation error: angle of q_pred * conj(q_true), degrees;
- penetration: max(0, floor_z - lowest world vertex z), % of the object's width;
- spin: the angle an object turns between successive frames, degrees, predicted and true (both
  from the orientations alike); the ratio of their means shows a model that turns objects too
  little or too much, which a rotation error alone does not tell apart;
- translation and rotation RMSE (the metrics of FIGNet, Allen et al. 2023, and of later work on
  Kubric's MOVi-A): the root of the mean over frames and objects of |p_pred - p_true|^2 in
  scene units (metres in MOVi-A) and of the rotation error^2 in degrees;
- interpenetration (scenes of several objects): for each pair of objects, the deepest vertex of
  either inside the other's convex hull (depth = min over the hull's faces of offset - n.x),
  % of the smaller object's width. A proxy of the convex-convex penetration depth: vertex-face
  only (an edge crossing an edge with no vertex inside counts 0); exact for convex meshes
  whose hull is the mesh, as the unit assets are.

Averaging order (see docs/metrics.md): per frame and object -> mean over the frames t >= start
of each object's trajectory -> mean over all objects of all scenes (each object trajectory
weighs the same, whatever its length). The default start = 0 includes the given initial frames,
as ContactNets averages over the whole toss; start = HISTORY (3) scores only the predicted frames.

Width = scale * largest extent of the rest mesh. The unit assets span exactly 1, so this is the
scale (2 for the real cube of half-width 1) as in the paper, and stays right if someone feeds a
mesh that does not span 1 (e.g. the ContactNets cube with vertices at +-1 and scale 1).

The formulas are numpy, no autograd: they score analytic simulators as well as the GNS. Only the
number of given frames comes from the model (gns.network.HISTORY).
"""
from __future__ import annotations

from collections import defaultdict
from typing import Mapping, Sequence

import numpy as np

from gns.network import HISTORY
from gns.geometry import pose_to_vertices, quat_to_matrix, rotation_angle

METRICS = ("position_error_pct", "rotation_error_deg", "penetration_pct")
DEFAULT_HORIZONS = (1, 5, 10, 20, 50, 100, 200)
# horizons (frames after the last given one) of named protocols: "240hz", that of later MOVi-A
# work on scenes recorded at 240 Hz (HOPNet, RigidFormer, RiCo: errors at 50, 75 and 100 frames)
PROTOCOLS = {"240hz": (50, 75, 100)}
# per frame besides METRICS: the truth's penetration, and the turn between frames of both
# the squares of the centre's distance (scene units) and of the rotation error behind the RMSEs
# FIGNet and later MOVi-A work report (translation_rmse, rotation_rmse_deg)
EXTRA = ("true_penetration_pct", "spin_deg", "true_spin_deg", "translation_sq", "rotation_sq_deg")


def object_width(scale, rest_vertices: np.ndarray) -> np.ndarray:
    """Width of a scaled unit asset: scale (...) * largest axis extent of the rest mesh (V, 3)."""
    extent = float(np.max(np.ptp(np.asarray(rest_vertices, np.float64), axis=0)))
    return np.asarray(scale, np.float64) * extent


def position_error_pct(pred_positions: np.ndarray, true_positions: np.ndarray, width) -> np.ndarray:
    """Centre distance as % of the width: (..., 3), (..., 3), width broadcastable to (...) -> (...)."""
    d = np.linalg.norm(np.asarray(pred_positions, np.float64) - np.asarray(true_positions, np.float64), axis=-1)
    return 100.0 * d / np.asarray(width, np.float64)


def rotation_error_deg(pred_quaternions: np.ndarray, true_quaternions: np.ndarray) -> np.ndarray:
    """Angle of q_pred * conj(q_true) in degrees, in [0, 180]: (..., 4), (..., 4) wxyz -> (...).
    q and -q are the same rotation and give 0."""
    return np.degrees(rotation_angle(pred_quaternions, true_quaternions))


def penetration_pct(positions: np.ndarray, quaternions: np.ndarray, scale, rest_vertices: np.ndarray,
                    floor_z: float = 0.0, width=None) -> np.ndarray:
    """max(0, floor_z - lowest world vertex z) as % of the width.

    positions (..., 3), quaternions (..., 4), scale scalar or (...), rest_vertices (V, 3) -> (...).
    width defaults to object_width(scale, rest_vertices).
    """
    verts = pose_to_vertices(positions, quaternions, scale, rest_vertices)  # (..., V, 3)
    lowest = verts[..., 2].min(axis=-1)
    if width is None:
        width = object_width(scale, rest_vertices)
    return 100.0 * np.maximum(0.0, floor_z - lowest) / np.asarray(width, np.float64)


def _hull(rest_vertices: np.ndarray) -> np.ndarray:
    """Face planes (F, 4) [n, offset] of the convex hull, n . x <= offset inside."""
    from scipy.spatial import ConvexHull
    eq = ConvexHull(np.asarray(rest_vertices, np.float64)).equations   # n . x + c <= 0 inside
    return np.concatenate([eq[:, :3], -eq[:, 3:]], axis=1)


def _depth_inside(points: np.ndarray, position: np.ndarray, quaternion: np.ndarray, scale: float,
                  planes: np.ndarray) -> np.ndarray:
    """Deepest of points (T, V, 3) inside the scaled hull at poses (T, 3), (T, 4): (T,), >= 0."""
    rot = quat_to_matrix(quaternion)                                      # (T, 3, 3)
    body = np.einsum("tji,tvj->tvi", rot, points - position[:, None]) / scale  # unit body frame
    depth = (planes[:, 3] - body @ planes[:, :3].T).min(axis=-1) * scale     # (T, V)
    return np.maximum(depth.max(axis=-1), 0.0)


# An object pair "passes through" when one's vertex gets this deep inside the other (% of the
# smaller width) at some frame: far beyond contact (PyBullet's own stays below 0.1%).
PASS_THROUGH_PCT = 10.0


def interpenetration_pct(scene, meshes: Mapping[str, tuple]) -> np.ndarray:
    """Per frame and object pair (a < b), the deepest vertex of one object inside the other,
    % of the smaller object's width: (T, P) with P = N (N - 1) / 2 (P = 0 for one object)."""
    T, N = scene.positions.shape[:2]
    scale = np.asarray(scene.scale, np.float64)
    rest = [np.asarray(meshes[s][0], np.float64) for s in scene.shape]
    verts = [pose_to_vertices(scene.positions[:, n], scene.quaternions[:, n], scale[n], rest[n]) for n in range(N)]
    planes = {s: _hull(meshes[s][0]) for s in set(scene.shape)}
    width = [float(object_width(scale[n], rest[n])) for n in range(N)]
    out = []
    for a in range(N):   # a few objects per scene; each pair is vectorised over frames and vertices
        for b in range(a + 1, N):
            depth = np.maximum(
                _depth_inside(verts[a], scene.positions[:, b], scene.quaternions[:, b], scale[b], planes[scene.shape[b]]),
                _depth_inside(verts[b], scene.positions[:, a], scene.quaternions[:, a], scale[a], planes[scene.shape[a]]))
            out.append(100.0 * depth / min(width[a], width[b]))
    return np.stack(out, axis=1) if out else np.zeros((T, 0))


def _check_pair(pred, true, i: int | None = None) -> None:
    where = "" if i is None else f"scene {i}: "
    if pred.positions.shape != true.positions.shape:
        raise ValueError(f"{where}predicted positions {pred.positions.shape} != true {true.positions.shape}")
    if pred.quaternions.shape != true.quaternions.shape:
        raise ValueError(f"{where}predicted quaternions {pred.quaternions.shape} != true {true.quaternions.shape}")


def per_frame_errors(pred, true, meshes: Mapping[str, tuple], floor_z: float = 0.0) -> dict[str, np.ndarray]:
    """Per-frame, per-object metrics of one predicted scene against the true one.

    pred, true: datagen.shards.Scene with the same (T, N); the object properties (shape, scale)
    are read from `true`. meshes: shape name -> (rest vertices (V, 3), faces).
    Returns METRICS plus "true_penetration_pct", "spin_deg" and "true_spin_deg" (frame 0: 0), each (T, N).
    """
    _check_pair(pred, true)
    T, N = true.positions.shape[:2]
    scale = np.asarray(true.scale, np.float64)
    out = {k: np.empty((T, N)) for k in METRICS + EXTRA}
    for n in range(N):  # objects can have different meshes; each call is vectorised over T
        rest = np.asarray(meshes[true.shape[n]][0], np.float64)
        width = object_width(scale[n], rest)
        out["position_error_pct"][:, n] = position_error_pct(pred.positions[:, n], true.positions[:, n], width)
        out["rotation_error_deg"][:, n] = rotation_error_deg(pred.quaternions[:, n], true.quaternions[:, n])
        out["translation_sq"][:, n] = ((pred.positions[:, n] - true.positions[:, n]) ** 2).sum(-1)
        out["rotation_sq_deg"][:, n] = out["rotation_error_deg"][:, n] ** 2
        out["penetration_pct"][:, n] = penetration_pct(pred.positions[:, n], pred.quaternions[:, n], scale[n],
                                                       rest, floor_z, width)
        out["true_penetration_pct"][:, n] = penetration_pct(true.positions[:, n], true.quaternions[:, n],
                                                            scale[n], rest, floor_z, width)
        for key, sc in (("spin_deg", pred), ("true_spin_deg", true)):
            out[key][0, n] = 0.0
            out[key][1:, n] = rotation_error_deg(sc.quaternions[1:, n], sc.quaternions[:-1, n])
    return out


def scene_errors(pred_scenes: Sequence, true_scenes: Sequence, meshes: Mapping[str, tuple],
                 floor_z: float = 0.0) -> list[dict[str, np.ndarray]]:
    """per_frame_errors of each pair of scenes, the pairs checked as evaluate_scenes checks them.

    The summaries below each take it as `errors`, so an evaluation computes it once."""
    if len(pred_scenes) != len(true_scenes):
        raise ValueError(f"{len(pred_scenes)} predicted scenes but {len(true_scenes)} true scenes")
    if not true_scenes:
        raise ValueError("no scenes to evaluate")
    out = []
    for i, (pred, true) in enumerate(zip(pred_scenes, true_scenes)):
        _check_pair(pred, true, i)
        out.append(per_frame_errors(pred, true, meshes, floor_z))
    return out


def per_frame_curves(pred_scenes: Sequence, true_scenes: Sequence, meshes: Mapping[str, tuple],
                     floor_z: float = 0.0, errors: Sequence[dict] | None = None) -> dict[str, np.ndarray]:
    """Mean over all objects of all scenes at each frame index, for error-vs-time plots.

    Scenes may differ in length: frame t averages the objects whose trajectory reaches t.
    Returns each metric as (T_max,) plus "count" (T_max,), the number of objects averaged.
    `errors`: the scenes' scene_errors, if already computed.
    """
    frames = errors if errors is not None else \
        [per_frame_errors(p, t, meshes, floor_z) for p, t in zip(pred_scenes, true_scenes, strict=True)]
    t_max = max(f["position_error_pct"].shape[0] for f in frames)
    sums = defaultdict(lambda: np.zeros(t_max))
    count = np.zeros(t_max)
    for f in frames:
        T, N = f["position_error_pct"].shape
        count[:T] += N
        for k, v in f.items():
            sums[k][:T] += v.sum(axis=1)
    with np.errstate(invalid="ignore"):
        out = {k: s / count for k, s in sums.items()}
    out["count"] = count
    return out


def per_scene_means(pred_scenes: Sequence, true_scenes: Sequence, meshes: Mapping[str, tuple],
                    floor_z: float = 0.0, start: int = 0, errors: Sequence[dict] | None = None) -> list[dict]:
    """Each scene's metrics averaged over its frames t >= start and its objects, with its
    scene_id: for paired comparisons of two simulators on the same scenes. `errors`: the
    scenes' scene_errors, if already computed."""
    out = []
    for k, (pred, true) in enumerate(zip(pred_scenes, true_scenes, strict=True)):
        f = errors[k] if errors is not None else per_frame_errors(pred, true, meshes, floor_z)
        row = {k: float(v[start:].mean()) for k, v in f.items()}
        sid = true.attrs.get("scene_id")
        row["scene_id"] = sid.item() if hasattr(sid, "item") else sid  # numpy scalars from HDF5 attributes
        out.append(row)
    return out


def _with_objects(pred, true):
    """pred's poses with true's object properties (a predicted scene may carry none of its own)."""
    from dataclasses import replace
    return replace(true, positions=pred.positions, quaternions=pred.quaternions)


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def _summary(rows: list[dict]) -> dict:
    """Mean of each metric over object rows (each row is one object trajectory's means)."""
    out = {k: _mean([r[k] for r in rows]) for k in METRICS + EXTRA}
    # predicted over true spin, summed over the group's objects (one object's ratio is noise when
    # it hardly turns); None when nothing turns
    out["spin_ratio"] = out["spin_deg"] / out["true_spin_deg"] if rows and out["true_spin_deg"] > 0 else None
    if rows:
        out["translation_rmse"] = float(np.sqrt(out["translation_sq"]))
        out["rotation_rmse_deg"] = float(np.sqrt(out["rotation_sq_deg"]))
    out["num_objects"] = len(rows)
    return out


def evaluate_scenes(pred_scenes: Sequence, true_scenes: Sequence, meshes: Mapping[str, tuple],
                    floor_z: float = 0.0, horizons: Sequence[int] = DEFAULT_HORIZONS, start: int = 0,
                    num_given: int = HISTORY, errors: Sequence[dict] | None = None) -> dict:
    """Score predicted scenes against the true ones; returns a JSON-ready dict.

    pred_scenes, true_scenes: matching lists of Scene (same T and N pairwise; T may vary between
    scenes). Each metric is averaged over frames t >= start of each object, then over all
    objects of all scenes. Keys:
      position_error_pct, rotation_error_deg, penetration_pct, true_penetration_pct (the
      ground truth's own penetration: the floor the predicted penetration can be compared to),
      num_scenes, num_objects, start, num_given, floor_z;
      horizons: {"h": {metrics..., num_objects}} at frame index num_given - 1 + h (h steps after
        the last given frame), over the objects whose trajectory is long enough; a horizon no
        trajectory reaches is left out;
      by_shape, by_size, by_material, by_objects: {value: {metrics..., num_objects}} (size is the
        scale, written with %g; objects the number of objects in the scene);
      translation_rmse, rotation_rmse_deg (also in each group).
    `errors`: the scenes' scene_errors, if already computed.
    """
    if errors is None:
        errors = scene_errors(pred_scenes, true_scenes, meshes, floor_z)
    rows = []                       # one row per object trajectory
    horizon_rows = defaultdict(list)
    for i, (true, f) in enumerate(zip(true_scenes, errors, strict=True)):
        T = true.num_frames
        if start >= T:
            raise ValueError(f"scene {i}: start={start} but the scene has only {T} frames")
        for n in range(true.num_objects):
            row = {k: float(v[start:, n].mean()) for k, v in f.items()}
            row.update(shape=true.shape[n], material=true.material[n], size=f"{float(true.scale[n]):g}",
                       objects=true.num_objects)
            rows.append(row)
            for h in horizons:
                t = num_given - 1 + int(h)
                if t < T:
                    horizon_rows[int(h)].append({k: float(v[t, n]) for k, v in f.items()})
    results = _summary(rows)
    results.update(num_scenes=len(true_scenes), start=int(start), num_given=int(num_given), floor_z=float(floor_z))
    if any(sc.num_objects > 1 for sc in true_scenes):
        # mean over object pairs of all scenes of each pair's mean over frames t >= start
        # and, per pair, its deepest frame: a mean over frames hides a pass-through in a few of them
        pairs = {k: [] for k in ("interpenetration_pct", "true_interpenetration_pct",
                                 "interpenetration_max_pct", "true_interpenetration_max_pct")}
        for pred, true in zip(pred_scenes, true_scenes):
            for prefix, sc in (("", pred), ("true_", true)):
                # object properties (shape, scale) are read from the true scene
                both = sc if sc is true else _with_objects(pred, true)
                depth = interpenetration_pct(both, meshes)[start:]
                pairs[f"{prefix}interpenetration_pct"] += list(depth.mean(axis=0))
                pairs[f"{prefix}interpenetration_max_pct"] += list(depth.max(axis=0))
        results.update({k: _mean([float(x) for x in v]) for k, v in pairs.items()})
        results["num_object_pairs"] = len(pairs["interpenetration_pct"])
        for prefix in ("", "true_"):
            deep = [x > PASS_THROUGH_PCT for x in pairs[f"{prefix}interpenetration_max_pct"]]
            results[f"{prefix}pairs_passing_through_pct"] = 100.0 * sum(deep) / max(len(deep), 1)
    results["horizons"] = {str(h): _summary(horizon_rows[h]) for h in sorted(horizon_rows)}
    for key in ("shape", "size", "material", "objects"):
        groups = defaultdict(list)
        for r in rows:
            groups[r[key]].append(r)
        results[f"by_{key}"] = {str(g): _summary(groups[g]) for g in sorted(groups)}
    return results


def bounding_gaps(sc, meshes: Mapping[str, tuple]) -> np.ndarray:
    """(T, N, N) the gap between the bounding spheres (radius: the farthest vertex of the scaled
    mesh) of each pair of objects of a scene at each frame; negative where they touch, inf on the
    diagonal. A cheap, model-free mark of where objects may be in contact."""
    r = np.array([np.linalg.norm(meshes[s][0], axis=1).max() for s in sc.shape]) * sc.scale
    gap = np.linalg.norm(sc.positions[:, :, None] - sc.positions[:, None], axis=-1) - (r[:, None] + r[None])
    gap[:, np.arange(sc.num_objects), np.arange(sc.num_objects)] = np.inf
    return gap


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3g}" if abs(v) < 0.1 else f"{v:.2f}"


def format_table(results: dict) -> str:
    """A plain-text table of evaluate_scenes' results for the terminal."""
    cols = ("position_error_pct", "rotation_error_deg", "penetration_pct", "true_penetration_pct", "spin_ratio",
            "num_objects")
    heads = ("pos %", "rot deg", "pen %", "true pen %", "spin/true", "objects")
    lines = [(f"all ({results['num_scenes']} scenes, frames >= {results['start']})",
              *[_fmt(results[c]) if c != "num_objects" else str(results[c]) for c in cols])]

    def add(title, group):
        for name, r in group.items():
            lines.append((f"{title} {name}", *[_fmt(r[c]) if c != "num_objects" else str(r[c]) for c in cols]))

    add("horizon", results.get("horizons", {}))
    add("shape", results.get("by_shape", {}))
    add("size", results.get("by_size", {}))
    add("material", results.get("by_material", {}))
    if len(results.get("by_objects", {})) > 1:
        add("objects", results["by_objects"])
    table = [("", *heads)] + lines
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    text = []
    for j, row in enumerate(table):
        text.append("  ".join([row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:])]))
        if j == 0:
            text.append("-" * len(text[0]))
    if results.get("translation_rmse") is not None:
        text.append(f"RMSE over frames and objects: translation {_fmt(results['translation_rmse'])} scene units, "
                    f"rotation {_fmt(results['rotation_rmse_deg'])} deg")
    if results.get("protocol"):
        at = [f"{h}: {_fmt(r['translation_rmse'])} m / {_fmt(r['rotation_rmse_deg'])} deg"
              for h, r in results["horizons"].items() if r.get("translation_rmse") is not None]
        text.append(f"{results['protocol']} protocol, RMSE at frames after the last given one: " + "; ".join(at))
    if "interpenetration_pct" in results:
        text.append(f"between objects ({results['num_object_pairs']} object pairs): "
                    f"interpenetration {_fmt(results['interpenetration_pct'])} % of size "
                    f"(true {_fmt(results['true_interpenetration_pct'])}), deepest frame "
                    f"{_fmt(results['interpenetration_max_pct'])} (true {_fmt(results['true_interpenetration_max_pct'])}), "
                    f"pairs deeper than {PASS_THROUGH_PCT:g}%: {_fmt(results['pairs_passing_through_pct'])}% "
                    f"(true {_fmt(results['true_pairs_passing_through_pct'])}%)")
    if results.get("num_diverged"):
        text.append(f"diverged: {results['num_diverged']} of {results['num_scenes'] + results['num_diverged']} scenes "
                    f"(inf or NaN positions, not in the table): {', '.join(map(str, results['diverged_scenes']))}")
    return "\n".join(text)
