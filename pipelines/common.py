"""Stages shared by the pipelines: each one skips itself when its output is already complete,
so rerunning a pipeline after an interruption continues where it stopped."""
from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from plumbing import config_dir, DataError, sigterm_as_interrupt
from datagen.scenes import load_config as load_scene_config
from datagen.toss import generate
from datagen.shards import Dataset
from gns.config import build_config, config_differences
from gns.evaluate import write_json
from gns.checkpoint import LATEST, CheckpointError, checkpoint_paths, resume_point
from gns.train import train

CONFIGS = config_dir()


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


class Costs:
    """Wall-clock seconds of the stages that ran, kept across resumed runs in costs.json."""

    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.exists() else {}

    def add(self, name: str, seconds: float) -> None:
        self.data[name] = round(seconds, 2)
        write_json(self.path, self.data)


def data_stage(out: Path, scene_sets: list[str], counts: dict[str, int], seed: int, workers: int) -> Dataset:
    """Generate a toss dataset unless `out` already holds the same one."""
    cfg = load_scene_config(sets=scene_sets)
    try:
        ds = Dataset(out)
        if ds.meta.get("config") == cfg and ds.meta.get("seed") == seed and \
                all(ds.num_scenes(s) == n for s, n in counts.items()):
            say(f"data: {out} is complete, skipping")
            return ds
        raise DataError("different dataset")
    except DataError:
        pass
    resume = (out / "metadata.json").exists()
    say(f"data: generating {sum(counts.values())} scenes into {out}")
    try:
        generate(cfg, seed, counts, out, workers=workers, resume=resume, overwrite=False)
    except DataError:
        if not resume:
            raise
        generate(cfg, seed, counts, out, workers=workers, overwrite=True)
    return Dataset(out)


def finished_dataset(out: Path, key: str, value, what: str) -> Dataset | None:
    """The dataset in `out` if its metadata records `key` = value (what it was made from), else None."""
    try:
        ds = Dataset(out)
    except DataError:
        return None
    if ds.meta.get(key) != value:
        return None
    say(f"{what}: {out} is complete, skipping")
    return ds


_STOPPED = []   # in a worker: set once a job of it was interrupted
ORPHAN_GRACE = 10.0   # seconds a worker of a vanished pipeline has to stop its job before it ends


def _watch_parent(parent: int) -> None:
    """In a worker, from its start: once the pipeline that made it is gone (killed outright,
    with no chance to stop its workers), stop as the pipeline would have asked (SIGTERM: a
    training checkpoints after its step) and end the process soon after. With no one to report
    to, a worker would otherwise finish its job, or wait for work, forever."""
    def watch():
        while os.getppid() == parent:
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(ORPHAN_GRACE)
        os._exit(1)
    threading.Thread(target=watch, daemon=True).start()


def _job_of(parent: int, fn, *args):
    """fn(*args) in a worker, unless the pipeline stopped it or has gone. A pool hands a worker
    one job ahead, which cancelling cannot take back: a worker whose training SIGTERM stopped
    would start it, and one orphaned by a killed pipeline would train beside a rerun."""
    if os.getppid() != parent:
        os._exit(1)   # no one to report to
    if _STOPPED:
        raise RuntimeError(f"job not started: the pipeline (process {parent}) stopped")
    try:
        return fn(*args)
    except KeyboardInterrupt:
        _STOPPED.append(True)
        raise


def in_processes(fn, jobs: dict, workers: int) -> dict:
    """{key: fn(*args)} for jobs {key: args}, `workers` at a time in processes of their own
    (spawned: no state is inherited, so fn must be a module's top-level function), or in this
    process with one worker. A failing job, Ctrl-C or SIGTERM to this process drops the jobs not
    started and passes SIGTERM on to the running ones (a training stops after its step with a
    checkpoint, as a training in one process does), then the failure is raised;
    workers whose pipeline was killed outright do the same by themselves (_watch_parent)."""
    if workers <= 1 or len(jobs) <= 1:
        return {key: fn(*args) for key, args in jobs.items()}
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    with sigterm_as_interrupt():
        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_watch_parent, initargs=(os.getpid(),)) as pool:
            futures = {key: pool.submit(_job_of, os.getpid(), fn, *args) for key, args in jobs.items()}
            try:
                return {key: f.result() for key, f in futures.items()}
            except BaseException:
                for f in futures.values():
                    f.cancel()               # the jobs not started yet are dropped, not run first
                for proc in list((getattr(pool, "_processes", None) or {}).values()):
                    if proc.is_alive():
                        proc.terminate()     # SIGTERM: a training checkpoints and stops
                pool.shutdown(cancel_futures=True)
                raise


def guarded(stages) -> int:
    """Run a pipeline's stages; a user error ends it with one `error:` line and exit status 2."""
    from gns.config import ConfigError
    from gns.evaluate import DivergedError
    from gns.train import TrainingError
    try:
        # SIGTERM as Ctrl-C in every stage: the same message, and whatever workers a stage
        # started are stopped the same way
        with sigterm_as_interrupt():
            stages()
    except (DataError, ConfigError, CheckpointError, TrainingError, DivergedError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a folder that became unwritable or a full disk after the checks
        print(f"error: {e.strerror or e}: {e.filename}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # a training stopped by Ctrl-C or SIGTERM says where it stopped
        print(f"error: interrupted{': ' + str(e) if str(e) else ''}; rerun the same command to go on", file=sys.stderr)
        return 130
    return 0


def remove_output(out: Path, names: set[str]) -> None:
    """--fresh: delete a pipeline's output folder, but only if everything in it has a name the
    pipeline writes (`names`), so a mistyped --out never deletes someone else's files."""
    if not out.exists():
        return
    if not out.is_dir():
        raise DataError(f"--out {out} is a file, not a pipeline output folder")
    # write_json's temporary files, left by a crash mid-write, are the pipeline's too
    foreign = sorted(p.name for p in out.iterdir()
                     if p.name not in names and not (p.name.startswith(".") and p.name.endswith(".tmp")))
    if foreign:
        shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more" if len(foreign) > 4 else "")
        raise DataError(f"--fresh refuses to delete {out}: it holds {shown}, which this pipeline does not write")
    say(f"fresh: deleting {out}")
    shutil.rmtree(out)


def trained_step(run: Path) -> int:
    """The step of a run's newest usable checkpoint, or -1 if it has none at all.

    A run whose checkpoints are all unreadable raises CheckpointError instead of counting as
    untrained: training from the start would delete them."""
    return resumable(run)[1]


def training_seconds(run: Path) -> float | None:
    """The seconds of training a run's newest checkpoint records (a stopped and resumed run's
    segments summed), or None for a run without one (or from before checkpoints kept them)."""
    _, ckpt, _ = _resume_point(run)
    return None if ckpt is None or "train_seconds" not in ckpt else float(ckpt["train_seconds"])


def resumable(run: Path) -> tuple[Path | None, int, str | None]:
    """(newest usable checkpoint, its step, a warning if it is not latest.pt), or (None, -1,
    None) for a run with no checkpoint file."""
    path, ckpt, note = _resume_point(run)
    return path, (-1 if ckpt is None else int(ckpt["step"])), note


def _resume_point(run: Path) -> tuple[Path | None, dict | None, str | None]:
    """`resume_point`, or (None, None, None) for a run with no checkpoint file."""
    if not (run / LATEST).exists() and not checkpoint_paths(run):
        return None, None, None
    return resume_point(run)


# settings that do not change what a run learns: a finished run is a result with any of them
# (train.compile changes the network's arithmetic only by rounding)
SETTINGS_FREE = ("train.steps", "train.threads", "train.device", "train.log_every", "train.checkpoint_every",
                 "train.keep_checkpoints", "train.compile", "valid.every", "valid.windows", "valid.rollout_scenes",
                 "valid.rollout_steps")


def train_stage(data: Path, run: Path, preset: str, overrides: list[str]) -> Path:
    """Train (or finish training) a run; skip when its checkpoint has reached the step count.
    Returns the checkpoint to evaluate: latest.pt, or the newest readable one if it is torn."""
    cfg = build_config(path=CONFIGS / f"gns_{preset}.toml", overrides=overrides)
    path, ckpt, note = _resume_point(run)
    step = -1 if ckpt is None else int(ckpt["step"])
    if ckpt is not None:
        # a run left by an earlier call with other settings is neither a result of these
        # settings (skipped) nor their start (resumed)
        changed = config_differences(ckpt["config"], cfg, ignore=SETTINGS_FREE)
        if changed:
            raise CheckpointError(f"{run} was trained with other settings ({'; '.join(changed[:3])}"
                                  f"{'; ...' if len(changed) > 3 else ''}): delete {run} (or the whole output with the "
                                  "pipeline's --fresh, where it has one) to train it again, or give another --out")
    if step >= cfg.train.steps:
        if note:
            say(note)
        say(f"train: {run} has reached step {step}, skipping")
        return path
    say(f"train: {run} ({preset} preset, {cfg.train.steps} steps" + (f", resuming at {step})" if step > 0 else ")"))
    train(data, run, cfg, resume=path is not None, overwrite=path is None, log=say)
    return run / LATEST


def zoo_model_as_run(name: str, data: Path, preset: str, overrides: list[str]) -> Path | None:
    """The file of zoo model `name` if it is what train_stage would make of `data` with these
    settings (the same training data, by fingerprint, and the same config but for SETTINGS_FREE),
    else None: a pipeline scores the model the zoo ships instead of training its twin."""
    from gns.checkpoint import checkpoint_of, read_checkpoint
    shipped = read_checkpoint(checkpoint_of(name))
    if shipped.get("provenance", {}).get("data", {}).get("fingerprint") != Dataset(data).fingerprint:
        return None
    cfg = build_config(path=CONFIGS / f"gns_{preset}.toml", overrides=overrides)
    if config_differences(shipped["config"], cfg, ignore=SETTINGS_FREE) or shipped["step"] != cfg.train.steps:
        return None
    return checkpoint_of(name)


def done(path: Path, checkpoint: Path) -> dict | None:
    """A stage's JSON output if it was made from this very checkpoint step (of its run folder,
    or of the file itself when it is not in one: a zoo model)."""
    if not path.exists():
        return None
    try:
        out = json.loads(path.read_text())
    except ValueError:  # torn by a crash mid-write: the stage runs again
        return None
    step = trained_step(checkpoint.parent)
    if step < 0 and checkpoint.is_file():
        from gns.checkpoint import read_checkpoint
        step = int(read_checkpoint(checkpoint)["step"])
    return out if out.get("checkpoint_step") == step else None
