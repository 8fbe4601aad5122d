"""What gns.api's Model.state is given, checked before any of it is used: each bad input is one
DataError line naming the argument (and the object), never an all-NaN trajectory or a numpy
error from deep inside (docs/reliability.md, the Python API rows).

Per-object vectors (positions, quaternions, velocities, angular velocities, history poses) need
one row per object: a single row is not repeated for several objects, which would start them in
one place. Per-object numbers (scales, friction, restitution) may be one number for all.
Everything must be finite and physical (sizes > 0, friction >= 0, restitution in [0, 1], no
object starting below the floor); a spin of half a turn per model step or more cannot be told
from a slower one by the model's input frames and is refused; objects starting inside each other
are warned about.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from plumbing import DataError

# An object may start this fraction of its scale below the floor: resting contact and measured
# (tracked) poses sink a little (the bound datagen.inspect allows a recorded frame, MAX_SINK_FRACTION).
FLOOR_TOLERANCE = 0.05
# the past frames of `history`, oldest first
PAST = ("t - 2 dt", "t - dt")


def _numbers(value, name: str) -> torch.Tensor:
    """value as a float64 tensor (a tensor keeps its autograd graph); one line on None, text,
    booleans, ragged lists or anything else that is not an array of numbers."""
    if value is None:
        raise DataError(f"{name} is None; give it (one row per object)")
    if isinstance(value, torch.Tensor):
        if value.dtype == torch.bool or value.is_complex():
            raise DataError(f"{name} must be real numbers, got a {value.dtype} tensor")
        return value.to(dtype=torch.float64)
    if isinstance(value, (str, bytes)):
        raise DataError(f"{name} must be numbers, got the text {value[:40]!r}")
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):
        a = np.empty(0, dtype=object)        # numpy refuses ragged nesting
    if a.dtype.kind in "USa":
        raise DataError(f"{name} must be numbers, got text")
    if a.dtype.kind == "b":
        raise DataError(f"{name} must be numbers, got booleans")
    if a.dtype.kind not in "iuf":
        raise DataError(f"{name} is ragged or holds something that is not a number; give an array of numbers")
    return torch.from_numpy(a.astype(np.float64))


def _values(t: torch.Tensor) -> str:
    return str([round(float(x), 6) for x in t.reshape(-1)]) if t.dim() else f"{float(t):g}"


def _finite(t: torch.Tensor, name: str, object_axis: int | None, frame_axis: int | None = None) -> None:
    bad = ~torch.isfinite(t.detach())
    if not bool(bad.any()):
        return
    index = bad.nonzero()[0].tolist() if t.dim() else []
    where = "" if object_axis is None else f" of object {index[object_axis]}"
    if frame_axis is not None:
        where += f" at {PAST[index[frame_axis]]}"
    row = t.detach()[tuple(index[:object_axis + 1])] if object_axis is not None else t.detach()
    raise DataError(f"{name}{where} is not finite ({_values(row)})")


def rows(value, name: str, b: int, width: int, device, frames: int | None = None) -> torch.Tensor:
    """(b, width), or (frames, b, width) for history poses: one row per object, finite. A row
    without its object axis is accepted for one object only."""
    t = _numbers(value, name)
    want = (b, width) if frames is None else (frames, b, width)
    if b == 1 and frames is None and tuple(t.shape) == (width,):
        t = t[None]
    if tuple(t.shape) != want:
        hint = " (one row per object; a single row is not repeated for several objects)" \
            if tuple(t.shape) in ((width,), (1, width)) and b > 1 else " (one row per object)"
        raise DataError(f"{name} has shape {tuple(t.shape)}, expected {want}{hint}")
    _finite(t, name, 0 if frames is None else 1, None if frames is None else 0)
    return t.to(device)


def quaternions(value, name: str, b: int, device, frames: int | None = None) -> torch.Tensor:
    """rows of 4, none of them zero (any non-zero length is normalised)."""
    q = rows(value, name, b, 4, device, frames)
    zero = q.detach().norm(dim=-1) < 1e-12
    if bool(zero.any()):
        index = zero.nonzero()[0].tolist()
        where = f" of object {index[-1]}" + ("" if frames is None else f" at {PAST[index[0]]}")
        raise DataError(f"{name}{where} is zero; give a rotation (any non-zero length)")
    return q


def per_object(value, name: str, b: int, device, check=None) -> torch.Tensor:
    """(b,) from one number or one per object, finite; `check(v) -> reason or None` on each value."""
    t = _numbers(value, name)
    if t.dim() and tuple(t.shape) != (b,):
        raise DataError(f"{name} has shape {tuple(t.shape)}, expected one number or ({b},) (one per object)")
    _finite(t, name, 0 if t.dim() else None)
    if check is not None:
        for i, v in enumerate(t.detach().reshape(-1).tolist()):
            reason = check(v)
            if reason:
                raise DataError(f"{name}{f' of object {i}' if t.dim() else ''} is {v:g}: {reason}")
    return (t.expand(b) if not t.dim() else t).to(device)


def positive(v: float) -> str | None:
    return None if v > 0 else "a size must be > 0"


def non_negative(v: float) -> str | None:
    return None if v >= 0 else "it must be >= 0"


def unit_interval(v: float) -> str | None:
    return None if 0 <= v <= 1 else "it must be in [0, 1]"


def shape_names(shapes, meshes: dict) -> list[str]:
    if shapes is None:
        raise DataError(f"shapes is None; give one mesh name per object ({', '.join(sorted(meshes))})")
    if isinstance(shapes, str):
        shapes = [shapes]
    try:
        shapes = list(shapes)
    except TypeError:
        raise DataError(f"shapes must be a list of mesh names, got {type(shapes).__name__}") from None
    for s in shapes:
        if not isinstance(s, str):
            raise DataError(f"shapes must be mesh names (text), got {s!r}")
    if not shapes:
        raise DataError("no objects given: shapes is empty")
    unknown = sorted(set(shapes) - set(meshes))
    if unknown:
        raise DataError(f"shape {unknown[0]!r} has no mesh in this model; it has {', '.join(sorted(meshes))}")
    return shapes


def scene_numbers(scene, b: int, device) -> torch.Tensor:
    if scene is None:
        return torch.zeros(b, dtype=torch.int64, device=device)
    what = "scene must be whole numbers (one scene number per object)"
    try:
        t = _numbers(scene.cpu() if isinstance(scene, torch.Tensor) else scene, "scene")
    except DataError as e:
        raise DataError(f"{what}, got {str(e).split(', got ')[-1] if ', got ' in str(e) else 'something else'}") from None
    if tuple(t.shape) != (b,):
        raise DataError(f"scene has shape {tuple(t.shape)}, expected ({b},): one scene number per object")
    if not bool(torch.isfinite(t).all()) or not bool((t == t.round()).all()):
        raise DataError(f"{what}, got {_values(t)[:60]}")
    return t.to(torch.int64).to(device)


def history_pair(history, b: int) -> tuple:
    if not isinstance(history, (tuple, list)) or len(history) != 2:
        raise DataError(f"history must be (positions ({len(PAST)}, {b}, 3), quaternions ({len(PAST)}, {b}, 4)): "
                        f"the poses at {' and '.join(PAST)}")
    return history[0], history[1]


def check_spin(angular_velocities: torch.Tensor, dt: float) -> None:
    """Refuse |w| dt >= pi: the model sees a spin only as the rotation between its input frames,
    and half a turn or more per step looks like a slower spin, or one backwards."""
    speed = angular_velocities.detach().norm(dim=-1)
    limit = math.pi / dt
    fast = speed * dt >= math.pi
    if bool(fast.any()):
        i = int(fast.nonzero()[0])
        raise DataError(f"angular_velocities of object {i}: {float(speed[i]):.4g} rad/s is half a turn or more per "
                        f"model step (limit pi / dt = {limit:.4g} rad/s at {1 / dt:g} steps/s): its input frames "
                        "would show a slower or backward spin")


def check_floor(frames, node_graph: torch.Tensor, scale: torch.Tensor, shapes: list[str], floor_z: float | None,
                given: list[int]) -> None:
    """Refuse an object whose lowest vertex starts deeper than FLOOR_TOLERANCE x its scale below
    the floor, in the frames `given` (indices into frames: the current one, and the history's if
    the user gave it; a free-flight extrapolation back in time may pass through the floor)."""
    if floor_z is None:
        return
    b = len(shapes)
    tol = FLOOR_TOLERANCE * scale.detach()
    for k in given:
        z = frames[k][:, 2].detach()
        low = torch.full((b,), math.inf, dtype=z.dtype, device=z.device).scatter_reduce(0, node_graph, z, "amin")
        deep = floor_z - low > tol
        if bool(deep.any()):
            i = int(deep.nonzero()[0])
            when = "" if k == len(frames) - 1 else f" at {PAST[k]}"
            raise DataError(f"object {i} ({shapes[i]}){when} starts {float(floor_z - low[i]):.3g} below the floor "
                            f"(z = {floor_z:g}; allowed {FLOOR_TOLERANCE:.0%} of its scale): move it up")


def inner_radius(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The radius of a ball about the mesh's origin inside it: the nearest face plane (exact for a
    convex mesh about its centre, smaller otherwise)."""
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12 * max(float(norm.max(initial=0)), 1e-300)
    if not ok.any():
        return 0.0
    return float(np.min(np.abs(np.einsum("ij,ij->i", n[ok], v[ok, 0])) / norm[ok]))


def overlapping_pairs(positions: np.ndarray, radii: np.ndarray, group: np.ndarray) -> tuple[int, tuple | None]:
    """(how many pairs of objects of one scene start inside each other, one such pair): centres
    nearer than the sum of their inner radii. A KD-tree query, so 1000 objects cost milliseconds."""
    from scipy.spatial import cKDTree
    if len(positions) < 2 or float(radii.max()) <= 0:
        return 0, None
    pairs = cKDTree(positions).query_pairs(2 * float(radii.max()), output_type="ndarray")
    if len(pairs) == 0:
        return 0, None
    i, j = pairs[:, 0], pairs[:, 1]
    inside = (np.linalg.norm(positions[i] - positions[j], axis=1) < radii[i] + radii[j]) & (group[i] == group[j])
    count = int(inside.sum())
    return count, (tuple(sorted((int(i[inside][0]), int(j[inside][0])))) if count else None)


def overlap_warning(shapes: list[str], meshes: dict, positions: torch.Tensor, scale: torch.Tensor,
                    group: torch.Tensor, collisions: bool) -> str | None:
    """One line if objects of one scene start inside each other, else None."""
    if len(shapes) < 2:
        return None
    inner = {name: inner_radius(*meshes[name]) for name in set(shapes)}
    radii = np.array([inner[s] for s in shapes]) * scale.detach().cpu().numpy()
    count, pair = overlapping_pairs(positions.detach().cpu().numpy(), radii, group.cpu().numpy())
    if not count:
        return None
    return (f"{count} pair{'s' if count > 1 else ''} of objects start inside each other (e.g. objects {pair[0]} and "
            f"{pair[1]}: their centres are nearer than their inscribed spheres allow); a rollout from there is not "
            "physical" + (", and every step of it is slow (collision edges between all their vertices)"
                          if collisions else ""))
