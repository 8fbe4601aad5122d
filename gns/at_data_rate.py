"""A model trained at every k-th recorded frame scored at every frame of the data (`gns eval
--at-data-rate`, and the 240hz protocol, which implies it), the instants any other simulator is
scored at: its rollout read between the frames it predicted (by the model file's reader, gns.between, or
a cubic spline). Loaded only when asked for.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from plumbing import DataError
from datagen.shards import Dataset, Scene, continuous, rotation, wxyz
from gns.evaluate import angular_velocities
from gns.metrics import PROTOCOLS


def check_protocol(protocol: str, data: str | Path) -> None:
    """Refuse, in one line, a protocol this code does not know or data it cannot be scored on."""
    if protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}")
    rate = Dataset(data).frame_rate
    if abs(rate - 240) > 1e-9:
        raise DataError(f"{data}: the 240hz protocol needs scenes recorded at 240 frames a second, these are at "
                        f"{rate:g} (datagen toss --set scene.frame_rate=240 scene.frames=461 records MOVi-A's 2 s)")


def reader_of(saved: dict, between: str = "learned"):
    """The reader between steps (gns.between) a model file holds, for `between` "learned"; None
    (read by the spline) for "spline" or a file without one."""
    if between not in ("learned", "spline"):
        raise DataError(f"between must be 'learned' or 'spline', got {between!r}")
    if between == "spline" or not saved.get("between"):
        return None
    from gns.between import BetweenReader
    return BetweenReader.from_state(saved["between"])


def read_every_frame(positions: np.ndarray, quaternions: np.ndarray, scale: np.ndarray, stride: int,
                     reader=None) -> tuple[np.ndarray, np.ndarray]:
    """Poses at every `stride`-th frame, centres (T, N, 3) and wxyz quaternions (T, N, 4) of
    objects of scales (N,), read at every frame between: by `reader` (a gns.between.BetweenReader
    of this stride) if given, else centres by a cubic spline (exact for free flight's parabolas; a
    bounce's kink rings by a small fraction of one coarse step's motion) and rotations by slerp.
    Returns ((T - 1) stride + 1, N, 3) and (.., N, 4), equal to the input at its own frames."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Slerp

    if reader is not None:
        if reader.stride != stride:
            raise DataError(f"the model's reader between steps reads a step of {reader.stride} frames, "
                            f"the rollout's step is {stride}")
        return reader.read(positions, quaternions, scale)
    coarse = np.arange(len(positions)) * stride
    fine = np.arange(coarse[-1] + 1)
    if len(coarse) > 2:
        fine_positions = CubicSpline(coarse, positions, axis=0)(fine)
    else:
        fine_positions = np.stack([np.interp(fine, coarse, c) for c in positions.reshape(len(coarse), -1).T],
                                  -1).reshape(len(fine), *positions.shape[1:])
    fine_quaternions = np.empty((len(fine), positions.shape[1], 4))
    for n in range(positions.shape[1]):
        if len(coarse) < 2:
            fine_quaternions[:, n] = quaternions[:, n]
            continue
        slerp = Slerp(coarse, rotation(quaternions[:, n]))
        fine_quaternions[:, n] = continuous(wxyz(slerp(fine).as_quat()))
    return fine_positions, fine_quaternions


def upsample_scene(pred: Scene, stride: int, true: Scene, frame_rate: float, reader=None) -> tuple[Scene, Scene]:
    """A rollout made at every `stride`-th frame, read at every frame of the full-rate truth it
    covers (read_every_frame). Returns (predicted, true), both cut to the frames up to the last
    predicted one, so a model with a coarser time step is scored at the same instants as one at
    the data's rate. frame_rate is the truth's (fine) rate."""
    positions, quaternions = read_every_frame(pred.positions, pred.quaternions, pred.scale, stride, reader)
    dt = 1.0 / frame_rate
    velocities = np.zeros_like(positions)
    velocities[1:] = (positions[1:] - positions[:-1]) / dt
    velocities[0] = true.velocities[0]
    cut = len(positions)
    upsampled = Scene(positions=positions, quaternions=quaternions, velocities=velocities,
                      angular_velocities=angular_velocities(quaternions, dt), shape=list(pred.shape),
                      material=list(pred.material), scale=pred.scale.copy(), mass=pred.mass.copy(),
                      friction=pred.friction.copy(), restitution=pred.restitution.copy(),
                      attrs={**pred.attrs, "upsampled_from_stride": stride,
                             "read_between": "spline" if reader is None else "learned"})
    truth = Scene(*(getattr(true, k)[:cut] for k in ("positions", "quaternions", "velocities", "angular_velocities")),
                  list(true.shape), list(true.material), true.scale, true.mass, true.friction, true.restitution,
                  dict(true.attrs))
    return upsampled, truth


def read_split_at_data_rate(pred: list[Scene], which: list[int], saved: dict, between: str, data: str | Path,
                            split: str, limit: int | None, stride: int) -> tuple[list[tuple[Scene, Scene]], Dataset, str]:
    """Rollouts `pred` at every `stride`-th frame of the split's scenes `which` (their indices in
    it), each read at every recorded frame by the model file's reader (`between`, reader_of):
    the (predicted, true) pairs of upsample_scene, the full-rate dataset, and how they were read
    ("learned" or "spline")."""
    reader = reader_of(saved, between)
    full = Dataset(data)
    truth = full.load(split, limit)
    pairs = [upsample_scene(p, stride, truth[i], full.frame_rate, reader) for p, i in zip(pred, which, strict=True)]
    return pairs, full, "spline" if reader is None else "learned"
