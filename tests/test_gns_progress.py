"""Training progress off a terminal (gns.run_folder): lines a batch job's log can show."""
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from gns_fixtures import write_toss_dataset

from gns.config import ConfigError
from gns.run_folder import ProgressLines, every_seconds, progress_bar

ROOT = Path(__file__).resolve().parent.parent
LINE = re.compile(r"step (\d+)/(\d+)  loss (\S+)  lr (\S+)  (\S+) steps/s(?:  eta (.+))?$")


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_a_line_every_interval_with_the_mean_loss_rate_and_eta():
    clock, lines = Clock(), []
    bar = ProgressLines(100, 0, lines.append, every=30.0, clock=clock)
    for step in range(1, 101):
        clock.now += 1.0          # one step a second
        bar.update(1)
        bar.set_postfix(loss=str(float(step)), lr="1e-3")
    bar.close()
    assert [LINE.match(s).group(1) for s in lines] == ["30", "60", "90", "100"]
    first = LINE.match(lines[0])
    assert float(first.group(3)) == pytest.approx(15.5)   # the mean of steps 1..30, not the last loss
    assert first.group(4) == "0.001" and float(first.group(5)) == pytest.approx(1.0)
    assert first.group(6) == "70 s"
    assert LINE.match(lines[-1]).group(6) is None           # the last step has nothing left


def test_a_stopped_training_logs_where_it_stopped_and_a_resumed_one_counts_from_its_step():
    clock, lines = Clock(), []
    bar = ProgressLines(1000, 400, lines.append, every=30.0, clock=clock)
    for _ in range(5):
        clock.now += 0.5
        bar.update(1)
        bar.set_postfix(loss="0.5", lr="2e-4")
    assert lines == []
    bar.close()
    assert lines == ["step 405/1000  loss 0.5  lr 0.0002  2 steps/s  eta 5 min"]


def test_a_terminal_gets_the_bar_and_a_pipe_the_lines():
    class Terminal(io.StringIO):
        def isatty(self):
            return True
    assert not isinstance(progress_bar(10, 0, print, stream=Terminal()), ProgressLines)
    assert isinstance(progress_bar(10, 0, print, stream=io.StringIO()), ProgressLines)
    assert not isinstance(progress_bar(10, 0, print, enabled=False, stream=io.StringIO()), ProgressLines)


def test_a_bad_interval_is_a_config_error(monkeypatch):
    monkeypatch.setenv("GNS_PROGRESS_SECONDS", "soon")
    with pytest.raises(ConfigError, match="GNS_PROGRESS_SECONDS='soon'"):
        every_seconds()
    monkeypatch.setenv("GNS_PROGRESS_SECONDS", "2.5")
    assert every_seconds() == 2.5


def test_gns_train_in_a_batch_job_logs_progress_lines(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=4, valid=1, frames=10)
    env = {**os.environ, "GNS_PROGRESS_SECONDS": "0.2", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    with open(tmp_path / "out.log", "w") as out, open(tmp_path / "err.log", "w") as err:
        done = subprocess.run([sys.executable, "-m", "gns.cli", "train", "--data", str(data), "--out",
                               str(tmp_path / "run"), "--config", "gns_tiny", "--steps", "300", "--set",
                               "valid.every=0"], stdout=out, stderr=err, stdin=subprocess.DEVNULL, cwd=ROOT,
                              env=env, timeout=300)
    text = (tmp_path / "out.log").read_text() + (tmp_path / "err.log").read_text()
    assert done.returncode == 0, text
    steps = [int(m.group(1)) for m in map(LINE.match, text.splitlines()) if m]
    assert len(steps) >= 2, text
    assert steps == sorted(set(steps)) and steps[-1] == 300
    assert "\r" not in text   # no bar redrawn into the log
