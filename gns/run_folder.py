"""The run folder a training writes and a resumed one reads back: metrics.jsonl, config.json,
provenance.json, TensorBoard events, and the checks made before a run starts over or goes on
(the checkpoints themselves are gns.checkpoint)."""
from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from gns.checkpoint import LATEST, CheckpointError, checkpoint_paths, resume_point
from gns.config import Config, ConfigError, build_config
from plumbing import atomic_file


METRICS = "metrics.jsonl"


PROVENANCE = "provenance.json"


TENSORBOARD_DIR = "tb"


def rng_state(rng: np.random.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "numpy": rng.bit_generator.state, "python": random.getstate()}


def restore_rng(state: dict, rng: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    rng.bit_generator.state = state["numpy"]
    random.setstate(state["python"])


def check_run(run: Path, resume: bool, overwrite: bool) -> list[Path]:
    """Refuse to start over a run's checkpoints unless asked; returns the files to delete."""
    existing = checkpoint_paths(run) + [p for p in (run / LATEST, run / METRICS, run / PROVENANCE) if p.exists()]
    existing += sorted((run / TENSORBOARD_DIR).glob("events.out.tfevents.*"))
    if resume:
        return []
    if any(p.suffix == ".pt" for p in existing) and not overwrite:
        raise CheckpointError(f"{run} already holds checkpoints; pass --resume to continue "
                              f"or --overwrite to start again")
    return existing


def _drop_metrics_after(path: Path, step: int, log: Callable[[str], None] = print) -> None:
    """Forget log lines of steps that a resumed run will train again (after a crash), and lines
    that are not JSON: a crash mid-write leaves the last one torn."""
    if not path.exists():
        return
    kept, torn = [], 0
    for line in path.read_text(errors="replace").splitlines():
        try:
            entry = json.loads(line)
            entry_step = int(entry["step"])
        except (ValueError, KeyError, TypeError):
            torn += bool(line.strip())
            continue
        if entry_step <= step:
            kept.append(line)
    if torn:
        log(f"warning: dropped {torn} unreadable line{'s' if torn > 1 else ''} of {path} "
            f"(a crash mid-write tears the last one)")
    with atomic_file(path) as tmp:
        tmp.write_text("".join(line + "\n" for line in kept))


def read_metrics(path: str | Path) -> list[dict]:
    """The entries of a metrics.jsonl, in order; lines that are not JSON objects with a step (a
    crash mid-write tears the last one) are skipped."""
    entries = []
    for line in Path(path).read_text(errors="replace").splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and isinstance(entry.get("step"), int):
            entries.append(entry)
    return entries


def tensorboard_writer(run: Path, purge_step: int | None):
    """A SummaryWriter on RUN/tb. On resume, events after the checkpoint's step (logged before a
    crash, trained again now) are purged, as _drop_metrics_after drops their metrics lines."""
    from torch.utils.tensorboard import SummaryWriter
    return SummaryWriter(log_dir=str(run / TENSORBOARD_DIR), purge_step=purge_step)


def check_tensorboard() -> None:
    """train.tensorboard needs the extra; checked before any work, one line."""
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        raise ConfigError("train.tensorboard=true needs TensorBoard: pip install 'rigid-gns[tensorboard]'") from None


def tensorboard_tag(key: str) -> str:
    """metrics.jsonl key -> TensorBoard tag, grouped as TensorBoard shows them: train/, valid/, speed/."""
    if key.startswith("valid_"):
        return "valid/" + key[len("valid_"):]
    if key.endswith("_per_sec"):
        return "speed/" + key
    return "train/" + key


def _log_scalars(writer, entry: dict) -> None:
    for key, value in entry.items():
        if key in ("step", "time") or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue   # None (all rollouts diverged) is not a scalar; counts and rates are
        writer.add_scalar(tensorboard_tag(key), value, entry["step"])
    writer.flush()


def run_provenance(data_dir: str | Path, fingerprint: str, step: int, earlier: dict | None) -> dict:
    """What a run records of where it came from: versions, code commit, the data it trained on;
    earlier runs of a resumed training are kept in `earlier`, oldest first."""
    from datagen.provenance import provenance
    history = []
    if isinstance(earlier, dict):
        history = [*earlier.get("earlier", []), {k: v for k, v in earlier.items() if k != "earlier"}]
    return {**provenance(), "data": {"path": str(data_dir), "fingerprint": fingerprint}, "start_step": step,
            "earlier": history}


def start_run_folder(run: Path, stale: list[Path], resumed_from: Path | None, step: int, config_dict: dict,
                      provenance: dict, log: Callable[[str], None]) -> None:
    """The run folder as this run of the training starts it: an earlier run's files deleted (--overwrite),
    metrics of steps to be trained again dropped (resume), config and provenance written."""
    for p in stale:
        p.unlink()
    run.mkdir(parents=True, exist_ok=True)
    if resumed_from:
        _drop_metrics_after(run / METRICS, step, log)
    for name, content in (("config.json", config_dict), (PROVENANCE, provenance)):
        with atomic_file(run / name) as tmp:
            tmp.write_text(json.dumps(content, indent=2) + "\n")


def write_metrics(metrics, writer, entry: dict) -> None:
    """One metrics.jsonl line, flushed so a crash loses nothing logged, and the TensorBoard scalars."""
    metrics.write(json.dumps(entry) + "\n")
    metrics.flush()
    if writer is not None:
        _log_scalars(writer, entry)


def resolve_config(run_dir: str | Path, resume: bool, config_path: str | None, overrides: list[str]) -> Config:
    """The config of a run: on resume the checkpoint's, updated by the file and overrides given."""
    base = None
    if resume and (checkpoint_paths(Path(run_dir)) or (Path(run_dir) / LATEST).exists()):
        base = resume_point(run_dir)[1]["config"]
    return build_config(base=base, path=config_path, overrides=overrides)
