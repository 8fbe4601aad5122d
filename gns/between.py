"""The frames between a strided model's steps, learned: `gns export --between DATA` fits it,
`gns eval --at-data-rate` reads by it. Loaded only when asked for.

A model that steps every k-th recorded frame (features.frame_stride = k) is scored at every
frame of the data, as any other simulator is. Its poses between its own frames used to be read by
a cubic spline through its centres and slerp between its orientations: that misses a tumble over
a table edge (the centre lifts and drops within a step) and the kink of an impact, and it cost
`real_cubes` 0.6 of its 6.8 points of position error (at its own frames it scores 6.2).

The reader is a small MLP fitted on the training data's own recorded frames. For each interval
between two of the model's frames j and j + 1 it reads the object's poses at j - 1 .. j + 2 (the
centres relative to the centre at j, the rotation matrices, the height kept absolute: the floor
is at a fixed height), turned about z so that the centre's horizontal motion over the interval
points along +x, and predicts, at each of the k - 1 frames between, the centre's offset from the
straight line between j and j + 1 and the rotation (a rotation vector) from the slerp between
them, turned back. So it keeps the model's own frames exactly, commutes with turns about z by
construction, and reads each object of a scene alone. Trained on the truth read at every k-th
frame (every phase), it is applied to the model's rollout.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from plumbing import DataError

HIDDEN = 256
# Adam steps of BATCH intervals, the learning rate falling to 0 on a cosine over PASSES passes
# through the intervals (60 fitted 256 real tosses no better on held-out ones; 3 passes over a
# few-toss GNS's 2000 engine tosses were 0.02-0.12 points worse on all six runs), at most
# MAX_STEPS: ~10 s of one thread for 256 tosses, ~90 s for 2000 and more
PASSES = 30
MAX_STEPS = 30000
BATCH = 256
LR = 1e-3
FRAMES = 4           # the model's frames a reading of one interval looks at: j - 1 .. j + 2
FEATURES = FRAMES * 3 + FRAMES * 9


def _turn(v: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Turn vectors (..., 3) about z by the angle whose cos, sin are c, s (broadcast to v[..., 0])."""
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def interval_features(positions: np.ndarray, quaternions: np.ndarray, scale: float):
    """One object's poses at the model's frames, centres (T, 3) and wxyz quaternions (T, 4) ->
    the features of its T - 1 intervals (T - 1, FEATURES), their turns (cos, sin: (T - 1,) each)
    and the rotations (a scipy Rotation of T)."""
    from datagen.shards import rotation
    T = len(positions)
    rot = rotation(quaternions)
    idx = np.clip(np.arange(T - 1)[:, None] + np.arange(-1, FRAMES - 1), 0, T - 1)     # (T - 1, 4)
    step = positions[1:, :2] - positions[:-1, :2]
    # the heading of the centre's motion; for an object that does not move sideways, of its
    # body's x axis (else y): a heading that turns with the scene wherever it is defined
    axes = rot.as_matrix()[:-1]
    axis = np.where((np.hypot(axes[:, 0, 0], axes[:, 1, 0]) > 1e-6)[:, None], axes[:, :2, 0], axes[:, :2, 1])
    step = np.where((np.hypot(step[:, 0], step[:, 1]) > 1e-9)[:, None], step, axis)
    angle = -np.arctan2(step[:, 1], step[:, 0])
    c, s = np.cos(angle), np.sin(angle)
    p = positions[idx].copy()
    p[..., :2] -= positions[:-1, None, :2]
    p = _turn(p, c[:, None], s[:, None])
    m = rot.as_matrix()[idx]                                    # (T - 1, 4, 3, 3): its columns turned
    m = np.swapaxes(_turn(np.swapaxes(m, -1, -2), c[:, None, None], s[:, None, None]), -1, -2)
    feats = np.concatenate([p.reshape(T - 1, -1), m.reshape(T - 1, -1) * scale], axis=1)
    return feats, (c, s), rot


def _chord(positions: np.ndarray, rot, stride: int):
    """The straight line between the model's frames and the slerp between its rotations, at the
    stride - 1 frames inside each interval: centres (T - 1, k - 1, 3), a Rotation of (T - 1)(k - 1)."""
    from scipy.spatial.transform import Slerp
    frac = np.arange(1, stride) / stride
    T = len(positions)
    centres = positions[:-1, None] + frac[:, None] * (positions[1:] - positions[:-1])[:, None]
    times = (np.arange(T - 1)[:, None] + frac).ravel()
    return centres, Slerp(np.arange(T), rot)(times)


def _check_stride(stride: int) -> None:
    if stride < 2:
        raise DataError("the model steps every recorded frame: there are no frames between its steps to read")


class BetweenReader(nn.Module):
    """Poses between a strided model's frames (module docstring). `stride`: the model's step in
    recorded frames."""

    def __init__(self, stride: int, hidden: int = HIDDEN):
        super().__init__()
        _check_stride(stride)
        self.stride, self.hidden = int(stride), int(hidden)
        out = 6 * (self.stride - 1)
        self.mlp = nn.Sequential(nn.Linear(FEATURES, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, out))
        for name, size in (("x_mean", FEATURES), ("x_std", FEATURES), ("y_mean", out), ("y_std", out)):
            self.register_buffer(name, torch.zeros(size, dtype=torch.float64))

    def to_state(self, **about) -> dict:
        """What an exported model file keeps (weights_only-loadable)."""
        return {"stride": self.stride, "hidden": self.hidden, "weights": self.state_dict(), **about}

    @classmethod
    def from_state(cls, state: dict) -> "BetweenReader":
        reader = cls(int(state["stride"]), int(state["hidden"]))
        reader.load_state_dict(state["weights"])
        return reader.eval()

    def _offsets(self, feats: np.ndarray) -> np.ndarray:
        # in numpy: a few intervals a toss through torch's threads waited ~10 ms a layer on a busy CPU
        if "_numpy" not in self.__dict__:
            layers = [m for m in self.mlp if isinstance(m, nn.Linear)]
            self.__dict__["_numpy"] = [(m.weight.detach().double().numpy().T, m.bias.detach().double().numpy())
                                       for m in layers]
        h = (feats - self.x_mean.numpy()) / self.x_std.numpy()
        for i, (w, b) in enumerate(self.__dict__["_numpy"]):
            h = h @ w + b
            if i < len(self.__dict__["_numpy"]) - 1:
                h = np.maximum(h, 0.0)
        return h * self.y_std.numpy() + self.y_mean.numpy()

    def read(self, positions: np.ndarray, quaternions: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A rollout at the model's frames, centres (T, N, 3), wxyz quaternions (T, N, 4), scales
        (N,) -> the same at every recorded frame: ((T - 1) k + 1, N, 3) and (.., N, 4), equal to
        the input at every k-th frame."""
        from scipy.spatial.transform import Rotation
        from datagen.shards import continuous, wxyz
        k, (T, N) = self.stride, positions.shape[:2]
        out_p = np.empty(((T - 1) * k + 1, N, 3))
        out_q = np.empty(((T - 1) * k + 1, N, 4))
        out_p[::k], out_q[::k] = positions, quaternions
        if T < 2:
            return out_p, out_q
        for n in range(N):
            feats, (c, s), rot = interval_features(positions[:, n], quaternions[:, n], float(scale[n]))
            centres, turns = _chord(positions[:, n], rot, k)
            y = self._offsets(feats).reshape(T - 1, 2, k - 1, 3)
            dc = _turn(y[:, 0], c[:, None], -s[:, None])
            dr = _turn(y[:, 1], c[:, None], -s[:, None]).reshape(-1, 3)
            inside = np.ones(len(out_p), dtype=bool)
            inside[::k] = False
            out_p[inside, n] = (centres + dc).reshape(-1, 3)
            out_q[inside, n] = wxyz((Rotation.from_rotvec(dr) * turns).as_quat())
            out_q[:, n] = continuous(out_q[:, n])
        return out_p, out_q


def training_pairs(scenes, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Features and targets of every interval of every object, read at every phase of `stride`
    from full-rate scenes: (M, FEATURES), (M, 6 (stride - 1))."""
    from datagen.shards import rotation
    X, Y = [], []
    for sc in scenes:
        fine_rot = [rotation(sc.quaternions[:, n]) for n in range(sc.num_objects)]
        for n in range(sc.num_objects):
            for phase in range(stride):
                pos, quat = sc.positions[phase::stride, n], sc.quaternions[phase::stride, n]
                T = len(pos)
                if T < 2:
                    continue
                feats, (c, s), rot = interval_features(pos, quat, float(sc.scale[n]))
                centres, turns = _chord(pos, rot, stride)
                fine = (phase + stride * np.arange(T - 1)[:, None] + np.arange(1, stride)).ravel()
                dc = sc.positions[fine, n].reshape(T - 1, stride - 1, 3) - centres
                dr = (fine_rot[n][fine] * turns.inv()).as_rotvec().reshape(T - 1, stride - 1, 3)
                X.append(feats)
                Y.append(np.concatenate([_turn(dc, c[:, None], s[:, None]).reshape(T - 1, -1),
                                         _turn(dr, c[:, None], s[:, None]).reshape(T - 1, -1)], axis=1))
    if not X:
        raise DataError(f"no scene has the {stride + 1} frames one step of the model spans")
    return np.concatenate(X), np.concatenate(Y)


def fit(scenes, stride: int, seed: int = 0, steps: int | None = None, progress: bool = False) -> BetweenReader:
    """A reader fitted on full-rate scenes (a dataset's train split, read at stride 1), on one
    thread: the same reader from the same data and seed on any machine's core count. `steps`
    default: PASSES passes over the intervals, at most MAX_STEPS."""
    X, Y = training_pairs(scenes, stride)
    if steps is None:
        steps = min(MAX_STEPS, -(-PASSES * len(X) // BATCH))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        reader = BetweenReader(stride)
        for name, v in (("x_mean", X.mean(0)), ("x_std", X.std(0) + 1e-6), ("y_mean", Y.mean(0)),
                        ("y_std", Y.std(0) + 1e-9)):
            getattr(reader, name).copy_(torch.from_numpy(v))
        x = ((torch.from_numpy(X) - reader.x_mean) / reader.x_std).float()
        y = ((torch.from_numpy(Y) - reader.y_mean) / reader.y_std).float()
        opt = torch.optim.Adam(reader.mlp.parameters(), LR)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
        from tqdm import tqdm
        order, at = torch.randperm(len(x), generator=gen), 0
        for _ in tqdm(range(steps), desc="fitting the reader between steps", unit="step", disable=not progress,
                      mininterval=2.0):
            if at >= len(x):       # the next pass over the intervals, in a new order
                order, at = torch.randperm(len(x), generator=gen), 0
            i = order[at:at + BATCH]
            at += BATCH
            loss = ((reader.mlp(x[i]) - y[i]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            schedule.step()
    finally:
        torch.set_num_threads(threads)
    return reader.eval()


def fit_on_data(ckpt: dict, data: str | Path, progress: bool = False) -> dict:
    """The reader of a model (a checkpoint dict) fitted on the train split of `data`, recorded at
    the rate the model steps k frames of: what export_model adds under "between"."""
    from datagen.shards import Dataset
    from gns.spec import ModelSpec
    stride = int(ckpt["config"]["features"].get("frame_stride", 1))
    _check_stride(stride)   # before the data are read
    ds = Dataset(data)
    want = ModelSpec.from_dict(ckpt["spec"]).frame_rate * stride
    if abs(ds.frame_rate - want) > 1e-6 * want:
        raise DataError(f"{data}: recorded at {ds.frame_rate:g} frames a second; the model steps {stride} frames "
                        f"of {want:g} a second")
    if "train" not in ds.splits:
        raise DataError(f"{data}: no train split to fit the reader between steps on")
    seed = int(ckpt.get("seed", 0))
    reader = fit(ds.load("train"), stride, seed=seed, progress=progress)
    return reader.to_state(data_fingerprint=ds.fingerprint, seed=seed)
