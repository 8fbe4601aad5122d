"""Training progress for a terminal and for batch jobs.

On a terminal, tqdm's bar. Off one (stderr a file or a pipe: a batch job, `nohup`, CI), tqdm
disables itself and nothing would say how far training is, so `progress_bar` returns a
`ProgressLines` instead: the same calls (update, set_postfix, close), one line every
GNS_PROGRESS_SECONDS (default 30) and at the last step:

    step 1200/20000  loss 0.0123  lr 4.1e-04  31.2 steps/s  eta 10 min
"""
from __future__ import annotations

import os
import sys
import time
from typing import Callable

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
