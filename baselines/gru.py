"""A recurrent baseline for one-cube tosses: a GRU over the cube's state, as Parmar et al. (2021).

    python -m baselines.gru train --data DIR --out RUN [--steps 3000] [--stride 8]
    python -m baselines.gru eval --run RUN --data DIR [--json FILE]

The state of a frame is the cube's centre (3), quaternion w x y z (4), linear and world-frame
angular velocity (3 + 3). The GRU reads the states of every `stride`-th frame (the GNS's time
step, features.frame_stride) and predicts each next state as a delta, s[t+1] = s[t] + f(s[..t]);
inputs and deltas are normalised by their training means and standard deviations. Training is
one-step prediction along whole tosses (teacher forcing) at every phase of the stride, with
Gaussian noise on the inputs (as the GNS's input noise) so that rollouts meet states a little
off the data; Adam, the GNS's learning-rate schedule (lr - lr_final shrinks 10x every
lr_decay_steps) and gradient clipping. A rollout is given the first 3 states (frames 0, k, 2k:
what the GNS is given), then feeds its own predictions back, the quaternion renormalised each
step. It is scored as `gns eval --at-data-rate` scores the GNS: its poses interpolated to every
recorded frame (centres by a cubic spline, rotations by slerp), position % and rotation degrees
by baselines.toss.toss_errors (the ContactNets metrics of gns.metrics), penetration of the cube's
corners, each averaged over the frames of a toss, then over tosses.
"""
from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Slerp

from baselines.toss import toss_errors
from datagen.shards import continuous, rotation, wxyz
from datagen.shards import Dataset, Scene
from plumbing import DataError, atomic_file

STATE = 13
GIVEN = 3
CHECKPOINT = "gru.pt"
PARTIAL = "gru_partial.pt"      # an unfinished run's state, deleted when gru.pt is written
SAVE_EVERY_SECONDS = 120.0
METRICS = "metrics.jsonl"


@dataclass(frozen=True)
class GRUConfig:
    hidden: int = 256            # Parmar et al.'s width
    layers: int = 2
    stride: int = 8              # frames per model step: the real-cube GNS's features.frame_stride
    steps: int = 3000            # optimiser steps
    batch_size: int = 32         # tosses (each at one phase of the stride) per step, the GNS's windows per step
    lr_init: float = 1e-3
    lr_final: float = 1e-6
    lr_decay_steps: int = 13333
    noise_std: float = 0.01      # input noise, in units of each input's standard deviation
    grad_clip: float = 1.0
    seed: int = 0
    log_every: int = 100


def scene_states(sc: Scene) -> np.ndarray:
    """(T, 13) states of a one-object scene."""
    if sc.num_objects != 1:
        raise DataError(f"the GRU baseline models one object a scene, got {sc.num_objects}")
    return np.concatenate([sc.positions[:, 0], sc.quaternions[:, 0], sc.velocities[:, 0],
                           sc.angular_velocities[:, 0]], axis=-1)


class GRUSimulator(torch.nn.Module):
    """GRU + linear head; normalisation of inputs and deltas held as buffers (saved with the weights)."""

    def __init__(self, hidden: int, layers: int, norm: dict[str, np.ndarray]):
        super().__init__()
        self.gru = torch.nn.GRU(STATE, hidden, num_layers=layers, batch_first=True)
        self.head = torch.nn.Linear(hidden, STATE)
        for k in ("mean", "std", "dmean", "dstd"):
            self.register_buffer(k, torch.as_tensor(np.asarray(norm[k]), dtype=torch.float32))

    def forward(self, states: torch.Tensor, h: torch.Tensor | None = None, noise: float = 0.0):
        """states (B, L, 13) -> (normalised deltas (B, L, 13), hidden)."""
        x = (states - self.mean) / self.std
        if noise:
            x = x + noise * torch.randn_like(x)
        y, h = self.gru(x, h)
        return self.head(y), h

    def delta(self, normalised: torch.Tensor) -> torch.Tensor:
        return normalised * self.dstd + self.dmean


def _sequences(scenes: list[Scene], stride: int) -> list[np.ndarray]:
    """Every toss at every phase of the stride: (L, 13) arrays of at least 2 states."""
    out = []
    for sc in scenes:
        s = scene_states(sc)
        out += [s[p::stride] for p in range(stride) if len(s[p::stride]) >= 2]
    return out


def normalisation(seqs: list[np.ndarray]) -> dict[str, np.ndarray]:
    states = np.concatenate([s[:-1] for s in seqs])
    deltas = np.concatenate([np.diff(s, axis=0) for s in seqs])
    return {"mean": states.mean(0), "std": np.maximum(states.std(0), 1e-6),
            "dmean": deltas.mean(0), "dstd": np.maximum(deltas.std(0), 1e-6)}


def _batch(seqs: list[np.ndarray], idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Padded inputs (B, L-1, 13), targets s[t+1] - s[t] and the mask of real steps."""
    L = max(len(seqs[i]) for i in idx)
    x, y, m = np.zeros((len(idx), L - 1, STATE)), np.zeros((len(idx), L - 1, STATE)), np.zeros((len(idx), L - 1))
    for b, i in enumerate(idx):
        s = seqs[i]
        x[b, :len(s) - 1], y[b, :len(s) - 1], m[b, :len(s) - 1] = s[:-1], np.diff(s, axis=0), 1.0
    return (torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32),
            torch.as_tensor(m, dtype=torch.float32))


def learning_rate(cfg: GRUConfig, step: int) -> float:
    return cfg.lr_final + (cfg.lr_init - cfg.lr_final) * 0.1 ** (step / cfg.lr_decay_steps)


def trained(out: str | Path, cfg: GRUConfig) -> bool:
    """Whether OUT holds a finished run of exactly this config."""
    path = Path(out) / CHECKPOINT
    if not path.exists():
        return False
    saved = torch.load(path, map_location="cpu", weights_only=False)
    return saved["config"] == asdict(cfg) and saved["step"] >= cfg.steps


def train(data: str | Path, out: str | Path, cfg: GRUConfig = GRUConfig(), log=None) -> Path:
    """Train on the train split of `data`; writes OUT/gru.pt (weights, normalisation, config,
    wall seconds) and OUT/metrics.jsonl (loss every log_every steps). A run whose checkpoint has
    reached cfg.steps with the same config is kept (returned without training).

    Resumable: every SAVE_EVERY_SECONDS, and on SIGINT or SIGTERM after the step under way (then
    KeyboardInterrupt), OUT/gru_partial.pt keeps the weights, Adam's moments and both random
    streams; a call with the same config and data goes on from it exactly, as if never stopped."""
    out = Path(out)
    path = out / CHECKPOINT
    if trained(out, cfg):
        return path
    ds = Dataset(data)
    seqs = _sequences(ds.load("train"), cfg.stride)
    if not seqs:
        raise DataError(f"{data}: no training toss has 2 states at stride {cfg.stride}")
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    norm = normalisation(seqs)
    model = GRUSimulator(cfg.hidden, cfg.layers, norm)
    from gns.train import adam
    opt = adam(model.parameters(), cfg.lr_init)
    out.mkdir(parents=True, exist_ok=True)
    step, lines, running, earlier = _resume(out, cfg, ds.fingerprint, model, opt, rng)
    if step and log:
        log(f"gru {out.name}: resuming at step {step}/{cfg.steps}")
    t0 = t_saved = time.perf_counter()

    def save_partial():
        with atomic_file(out / PARTIAL) as tmp:
            torch.save({"config": asdict(cfg), "data_fingerprint": ds.fingerprint, "step": step,
                        "state_dict": model.state_dict(), "optimizer": opt.state_dict(),
                        "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(), "lines": lines,
                        "running": running, "train_seconds": earlier + time.perf_counter() - t0}, tmp)

    from gns.run_folder import StopRequest
    with StopRequest() as stop:
        while step < cfg.steps:
            for g in opt.param_groups:
                g["lr"] = learning_rate(cfg, step)
            x, y, m = _batch(seqs, rng.integers(len(seqs), size=cfg.batch_size))
            pred, _ = model(x, noise=cfg.noise_std)
            err = ((pred - (y - model.dmean) / model.dstd) ** 2).mean(-1)
            loss = (err * m).sum() / m.sum()
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            running.append(loss.item())
            step += 1
            if step % cfg.log_every == 0 or step == cfg.steps:
                lines.append({"step": step, "loss": float(np.mean(running)), "lr": learning_rate(cfg, step - 1),
                              "seconds": round(earlier + time.perf_counter() - t0, 2)})
                running = []
                if log and (step % (10 * cfg.log_every) == 0 or step == cfg.steps):
                    log(f"gru {out.name}: step {step}/{cfg.steps} loss {lines[-1]['loss']:.4g}")
            if stop.asked:
                save_partial()
                raise KeyboardInterrupt(f"{stop.asked}: GRU stopped at step {step} of {cfg.steps}, saved in "
                                        f"{out / PARTIAL}; the same call goes on from there")
            if time.perf_counter() - t_saved > SAVE_EVERY_SECONDS and step < cfg.steps:
                save_partial()
                t_saved = time.perf_counter()
    seconds = earlier + time.perf_counter() - t0
    with atomic_file(out / METRICS) as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in lines))
    with atomic_file(path) as tmp:
        torch.save({"config": asdict(cfg), "step": cfg.steps, "state_dict": model.state_dict(),
                    "norm": {k: v.tolist() for k, v in norm.items()}, "train_seconds": seconds,
                    "data": str(data), "data_fingerprint": ds.fingerprint, "num_train": ds.num_scenes("train")}, tmp)
    (out / PARTIAL).unlink(missing_ok=True)
    return path


def _resume(out: Path, cfg: GRUConfig, fingerprint: str, model: GRUSimulator, opt: torch.optim.Optimizer,
            rng: np.random.Generator) -> tuple[int, list, list, float]:
    """(step, metrics lines, losses since the last line, seconds trained) of OUT/gru_partial.pt
    loaded into the model, optimiser and random streams; (0, [], [], 0.0) when there is none,
    or it holds another config or data (it is then overwritten at the next save)."""
    try:
        saved = torch.load(out / PARTIAL, map_location="cpu", weights_only=False)
    except (OSError, RuntimeError, EOFError, ValueError, pickle.UnpicklingError):   # absent or torn: from the start
        return 0, [], [], 0.0
    if saved.get("config") != asdict(cfg) or saved.get("data_fingerprint") != fingerprint:
        return 0, [], [], 0.0
    model.load_state_dict(saved["state_dict"])
    opt.load_state_dict(saved["optimizer"])
    rng.bit_generator.state = saved["rng"]
    torch.set_rng_state(saved["torch_rng"])
    return int(saved["step"]), saved["lines"], saved["running"], float(saved["train_seconds"])


def load(run: str | Path) -> tuple[GRUSimulator, dict]:
    path = Path(run)
    path = path / CHECKPOINT if path.is_dir() else path
    if not path.is_file():
        raise DataError(f"no GRU checkpoint at {path}")
    saved = torch.load(path, map_location="cpu", weights_only=False)
    cfg = saved["config"]
    model = GRUSimulator(cfg["hidden"], cfg["layers"], {k: np.array(v) for k, v in saved["norm"].items()})
    model.load_state_dict(saved["state_dict"])
    model.eval()
    return model, saved


@torch.no_grad()
def rollout_states(model: GRUSimulator, given: np.ndarray, steps: int) -> np.ndarray:
    """(given + steps, 13) states at the model's step: the given ones, then its own predictions."""
    states = [np.asarray(s, np.float64) for s in given]
    out, h = model(torch.as_tensor(np.stack(states)[None], dtype=torch.float32))
    d = model.delta(out[0, -1]).double().numpy()
    for _ in range(steps):
        s = states[-1] + d
        s[3:7] /= max(np.linalg.norm(s[3:7]), 1e-12)
        states.append(s)
        out, h = model(torch.as_tensor(s[None, None], dtype=torch.float32), h)
        d = model.delta(out[0, -1]).double().numpy()
    return np.stack(states)


def rollout_scene(model: GRUSimulator, sc: Scene, stride: int, given: int = GIVEN) -> tuple[Scene, Scene]:
    """The GRU's rollout of a toss from its states at frames 0, k, .., (given-1)k, interpolated to
    every recorded frame up to its last step; returns (predicted, truth cut to the same frames)."""
    s = scene_states(sc)
    coarse = s[::stride]
    if len(coarse) <= given:
        raise DataError(f"a toss of {sc.num_frames} frames is too short for {given} given states at stride {stride}")
    pred = rollout_states(model, coarse[:given], len(coarse) - given)
    frames = np.arange(len(pred)) * stride
    fine = np.arange(frames[-1] + 1)
    pos = CubicSpline(frames, pred[:, :3], axis=0)(fine)
    rots = rotation(pred[:, 3:7])
    quat = continuous(wxyz(Slerp(frames, rots)(fine).as_quat()))
    vel = np.stack([np.interp(fine, frames, c) for c in pred[:, 7:10].T], -1)
    ang = np.stack([np.interp(fine, frames, c) for c in pred[:, 10:13].T], -1)
    n = len(fine)
    out = Scene(positions=pos[:, None], quaternions=quat[:, None], velocities=vel[:, None],
                angular_velocities=ang[:, None], shape=list(sc.shape), material=list(sc.material),
                scale=sc.scale.copy(), mass=sc.mass.copy(), friction=sc.friction.copy(),
                restitution=sc.restitution.copy(), attrs={**sc.attrs, "baseline": "gru", "stride": stride})
    truth = replace(sc, positions=sc.positions[:n], quaternions=sc.quaternions[:n], velocities=sc.velocities[:n],
                    angular_velocities=sc.angular_velocities[:n])
    return out, truth


def penetration_pct(sc: Scene, floor_z: float = 0.0) -> float:
    """Mean over frames of how deep the cube's lowest corner is below the floor, % of its width."""
    width = float(sc.scale[0])
    corners = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]) * width
    low = (np.einsum("tij,vj->tvi", rotation(sc.quaternions[:, 0]).as_matrix(), corners)[..., 2]
           + sc.positions[:, 0, 2:3]).min(axis=1)
    return float((100.0 * np.maximum(0.0, floor_z - low) / width).mean())


def evaluate(run: str | Path, data: str | Path, split: str = "test") -> dict:
    """Roll out and score every toss of a split (see the module doc); results in gns eval's keys."""
    model, saved = load(run)
    ds = Dataset(data)
    floor_z = float(ds.floor["z"]) if ds.floor else 0.0
    t0 = time.perf_counter()
    per_scene = []
    for i, sc in enumerate(ds.load(split)):
        pred, truth = rollout_scene(model, sc, saved["config"]["stride"])
        pos, rot = toss_errors(pred, truth)
        if not (math.isfinite(pos) and math.isfinite(rot)):
            raise DataError(f"the GRU's rollout of scene {i} diverged")
        per_scene.append({"scene_id": sc.attrs.get("scene_id", i), "position_error_pct": pos, "rotation_error_deg": rot,
                          "penetration_pct": penetration_pct(pred, floor_z),
                          "true_penetration_pct": penetration_pct(truth, floor_z)})
    keys = ("position_error_pct", "rotation_error_deg", "penetration_pct", "true_penetration_pct")
    return {**{k: float(np.mean([r[k] for r in per_scene])) for k in keys}, "num_scenes": len(per_scene),
            "at_data_rate": True, "model_stride": saved["config"]["stride"], "rollout_seconds": time.perf_counter() - t0,
            "run": str(run), "data": str(data), "split": split, "checkpoint_step": saved["step"],
            "train_seconds": saved["train_seconds"], "per_scene": per_scene}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m baselines.gru", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train a GRU on the train split of a dataset")
    t.add_argument("--data", required=True)
    t.add_argument("--out", required=True)
    for f in ("steps", "stride", "hidden", "layers", "batch_size", "seed", "lr_decay_steps"):
        t.add_argument(f"--{f.replace('_', '-')}", type=int, default=getattr(GRUConfig, f))
    e = sub.add_parser("eval", help="roll out and score a trained GRU")
    e.add_argument("--run", required=True)
    e.add_argument("--data", required=True)
    e.add_argument("--split", default="test")
    e.add_argument("--json")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    try:
        if a.cmd == "train":
            cfg = GRUConfig(**{f: getattr(a, f) for f in ("steps", "stride", "hidden", "layers", "batch_size", "seed",
                                                            "lr_decay_steps")})
            print(f"wrote {train(a.data, a.out, cfg, log=lambda m: print(m, file=sys.stderr))}")
        else:
            r = evaluate(a.run, a.data, a.split)
            print(f"{r['num_scenes']} tosses: position {r['position_error_pct']:.2f}%, rotation "
                  f"{r['rotation_error_deg']:.2f} deg, penetration {r['penetration_pct']:.2f}% "
                  f"(truth {r['true_penetration_pct']:.2f}%)")
            if a.json:
                Path(a.json).write_text(json.dumps(r, indent=1) + "\n")
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
