"""TensorBoard event files beside metrics.jsonl, for train.tensorboard (the tensorboard extra);
a run that does not ask for them never loads this module.
"""
from __future__ import annotations

from pathlib import Path

from gns.config import ConfigError
from gns.run_folder import TENSORBOARD_DIR


def tensorboard_writer(run: Path, purge_step: int | None):
    """A SummaryWriter on RUN/tb. On resume, events after the checkpoint's step (logged before a
    crash, trained again now) are purged, as gns.run_folder drops their metrics lines."""
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


def log_scalars(writer, entry: dict) -> None:
    for key, value in entry.items():
        if key in ("step", "time") or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue   # None (all rollouts diverged) is not a scalar; counts and rates are
        writer.add_scalar(tensorboard_tag(key), value, entry["step"])
    writer.flush()
