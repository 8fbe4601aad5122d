"""Stages shared by the pipelines: each one skips itself when its output is already complete,
so rerunning a pipeline after an interruption continues where it stopped."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from datagen.config import config_dir, load_config as load_scene_config
from datagen.generate import generate
from datagen.shards import Dataset, DataError
from gns.config import build_config
from gns.train import LATEST, CheckpointError, resume_checkpoint, train

CONFIGS = config_dir()


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


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


def guarded(stages) -> int:
    """Run a pipeline's stages; a user error ends it with one `error:` line and exit status 2."""
    from gns.config import ConfigError
    from gns.train import CheckpointError, TrainingError
    try:
        stages()
    except (DataError, ConfigError, CheckpointError, TrainingError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


def trained_step(run: Path) -> int:
    """The step of the checkpoint a rerun would resume from (latest.pt, else the newest readable
    ckpt-*.pt), -1 if there is none: a damaged latest.pt must not restart (and delete) a run."""
    try:
        return int(resume_checkpoint(run)[1]["step"])
    except CheckpointError:
        return -1


def train_stage(data: Path, run: Path, preset: str, overrides: list[str]) -> Path:
    """Train (or finish training) a run; skip when its checkpoint has reached the step count."""
    cfg = build_config(path=CONFIGS / f"gns_{preset}.toml", overrides=overrides)
    step = trained_step(run)
    if step >= cfg.train.steps:
        say(f"train: {run} has reached step {step}, skipping")
        return resume_checkpoint(run, say)[0]
    say(f"train: {run} ({preset} preset, {cfg.train.steps} steps" + (f", resuming at {step})" if step > 0 else ")"))
    train(data, run, cfg, resume=step > 0, overwrite=step <= 0, log=say)
    return run / LATEST


def done(path: Path, checkpoint: Path) -> dict | None:
    """A stage's JSON output if it was made from this very checkpoint step."""
    if not path.exists():
        return None
    out = json.loads(path.read_text())
    return out if out.get("checkpoint_step") == trained_step(checkpoint.parent) else None
