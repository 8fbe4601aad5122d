"""The run folder a training writes and a resumed one reads back (metrics.jsonl, config.json,
provenance.json), where the run runs (its device, threads and place among torchrun processes),
the progress lines of a run off a terminal, the signals that stop it, and the checks made before
a run starts over or goes on. The checkpoints themselves are gns.checkpoint's; TensorBoard's
event files, written only with train.tensorboard, gns.tensorboard_log's."""
from __future__ import annotations

import json
import os
import random
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from gns.checkpoint import LATEST, CheckpointError, checkpoint_paths, parse_device, resume_point
from gns.config import Config, ConfigError, build_config
from plumbing import atomic_file, check_writable


METRICS = "metrics.jsonl"


PROVENANCE = "provenance.json"


# TensorBoard event files (gns.tensorboard_log) go here: an overwrite deletes them with the rest
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


def run_provenance(data_dir: str | Path, fingerprint: str, step: int, earlier: dict | None) -> dict:
    """What a run records of where it came from: versions, code commit, the data it trained on;
    earlier runs of a resumed training are kept in `earlier`, oldest first."""
    from plumbing import provenance
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
        from gns.tensorboard_log import log_scalars
        log_scalars(writer, entry)


def resolve_config(run_dir: str | Path, resume: bool, config_path: str | None, overrides: list[str]) -> Config:
    """The config of a run: on resume the checkpoint's, updated by the file and overrides given."""
    base = None
    if resume and (checkpoint_paths(Path(run_dir)) or (Path(run_dir) / LATEST).exists()):
        base = resume_point(run_dir)[1]["config"]
    return build_config(base=base, path=config_path, overrides=overrides)


EVERY_SECONDS = 30.0
ENV = "GNS_PROGRESS_SECONDS"


def progress_bar(total: int, initial: int, log: Callable[[str], None], enabled: bool = True, stream=None):
    """tqdm on a terminal; ProgressLines through `log` off one; nothing (a disabled tqdm) when not
    `enabled` (a training process other than the first)."""
    from tqdm import tqdm
    stream = sys.stderr if stream is None else stream
    if not enabled or _is_terminal(stream):
        return tqdm(total=total, initial=initial, unit="step", disable=not enabled, dynamic_ncols=True, file=stream)
    return ProgressLines(total, initial, log, every_seconds())


def every_seconds() -> float:
    text = os.environ.get(ENV)
    if text is None:
        return EVERY_SECONDS
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0:
        from gns.config import ConfigError   # one line from `gns train`, not a traceback
        raise ConfigError(f"{ENV}={text!r}: seconds between progress lines, a number >= 0")
    return value


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):   # no isatty, or a closed stream
        return False


class ProgressLines:
    """tqdm's update / set_postfix / close, written as a line every `every` seconds of wall clock.

    The loss shown is the mean over the steps since the last line (one step's loss is noise);
    steps/s and the ETA are measured over the same stretch, so they follow a machine's changing load."""

    def __init__(self, total: int, initial: int, log: Callable[[str], None], every: float = EVERY_SECONDS,
                 clock: Callable[[], float] = time.monotonic):
        self.total, self.step, self.log, self.every, self.clock = total, initial, log, every, clock
        self.mark_time, self.mark_step = clock(), initial
        self.loss_sum, self.loss_count, self.lr = 0.0, 0, None
        self.last_logged = initial

    def update(self, n: int = 1) -> None:
        self.step += n

    def set_postfix(self, loss=None, lr=None, refresh: bool = False, **_ignored) -> None:
        """The step's loss and learning rate (tqdm's call after each update): a line when one is due."""
        if loss is not None:
            self.loss_sum += float(loss)
            self.loss_count += 1
        if lr is not None:
            self.lr = float(lr)
        if self.step >= self.total or self.clock() - self.mark_time >= self.every:
            self.log(self._line())

    def close(self) -> None:
        if self.step != self.last_logged:   # steps since the last line (a training stopped early)
            self.log(self._line())

    def _line(self) -> str:
        now = self.clock()
        steps, seconds = self.step - self.mark_step, now - self.mark_time
        parts = [f"step {self.step}/{self.total}"]
        if self.loss_count:
            parts.append(f"loss {self.loss_sum / self.loss_count:.4g}")
        if self.lr is not None:
            parts.append(f"lr {self.lr:.2g}")
        if steps > 0 and seconds > 0:
            rate = steps / seconds
            parts.append(f"{rate:.3g} steps/s")
            if self.total > self.step:
                parts.append(f"eta {_duration((self.total - self.step) / rate)}")
        self.mark_time, self.mark_step, self.loss_sum, self.loss_count = now, self.step, 0.0, 0
        self.last_logged = self.step
        return "  ".join(parts)


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class StopRequest:
    """SIGINT and SIGTERM, while installed, ask the loop to stop after the step under way (a
    checkpoint of a half-done Adam step would not resume exactly); a second signal stops at once.
    One process only: processes of a parallel run stopping at different steps would hang."""

    def __init__(self):
        self.asked, self.previous = None, {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.previous[sig] = signal.signal(sig, self._ask)
        return self

    def _ask(self, signum, frame):
        if self.asked is not None:  # asked twice: do not wait for the step
            raise KeyboardInterrupt
        self.asked = signal.Signals(signum).name

    def __exit__(self, *exc):
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        return False


# Where the run runs: its device and threads, and its place among the processes of a torchrun
# training (gns.processes, loaded only when there are several).


@dataclass(frozen=True)
class World:
    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """The process that writes checkpoints, metrics and logs."""
        return self.rank == 0


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name, str(default))
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f"environment variable {name}={value!r} is not an integer (set by torchrun)") from None


def world_from_env() -> World:
    """This process's place among the torchrun processes (one process when not launched by torchrun)."""
    return World(_env_int("RANK", 0), _env_int("WORLD_SIZE", 1), _env_int("LOCAL_RANK", 0))


def training_device(name: str, world: World = World()) -> torch.device:
    device = parse_device(name)
    if world.size > 1 and device.type == "cuda":
        return torch.device("cuda", world.local_rank)  # torchrun: one GPU per process
    if world.size > 1 and device.type == "mps":
        raise ConfigError("training on several processes runs on cpu or cuda, not mps")
    return device


def set_threads(threads: int, log: Callable[[str], None]) -> None:
    """Use `threads` (0 = all cores), warning when other processes already load the cores:
    OpenMP threads that get descheduled stall every parallel region (measured: 16 -> 0.6 steps/s)."""
    cores = os.cpu_count() or 1
    threads = threads or cores
    torch.set_num_threads(threads)
    load = os.getloadavg()[0]
    if threads > 1 and load + threads > cores + 0.5:
        log(f"warning: {threads} threads on {cores} cores with a load average of {load:.1f}; "
            f"if steps/s collapse, use --set train.threads=1")


def check_start(run: Path, cfg: Config, world: World, resume: bool, overwrite: bool,
                 log: Callable[[str], None]) -> tuple[list[Path], torch.device, tuple[Path, dict] | None]:
    """Everything checked before the data is read: the batch split, the run folder, the device,
    the checkpoint to resume, the extras asked for. Returns (files of an earlier run to delete,
    device, (checkpoint path, checkpoint) when resuming)."""
    if world.size > 1 and cfg.train.batch_size < world.size:
        raise ConfigError(f"train.batch_size={cfg.train.batch_size} is the global batch, split over "
                          f"{world.size} processes: it must be at least {world.size}")
    stale = check_run(run, resume, overwrite)
    device = training_device(cfg.train.device, world)
    resumed = None
    if resume:
        path, ckpt, note = resume_point(run)
        if note:
            log(note)
        resumed = (path, ckpt)
    if world.main:
        check_writable(run, "run folder")
    if cfg.train.tensorboard:
        from gns.tensorboard_log import check_tensorboard
        check_tensorboard()
    return stale, device, resumed
