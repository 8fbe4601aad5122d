"""pipelines.common.in_processes: the pipelines' --workers."""
import os

import pytest

from pipelines.common import in_processes
from plumbing import DataError


def square_in_a_process(k: int) -> tuple[int, int]:
    if k < 0:
        raise DataError(f"job {k} failed")
    return k * k, os.getpid()


@pytest.mark.parametrize("workers", [1, 2])
def test_every_job_once_by_its_key(workers):
    out = in_processes(square_in_a_process, {f"j{k}": (k,) for k in range(5)}, workers)
    assert {key: value for key, (value, _) in out.items()} == {f"j{k}": k * k for k in range(5)}
    pids = {pid for _, pid in out.values()}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids and len(pids) <= 2)


def test_a_failing_job_raises_its_own_error():
    with pytest.raises(DataError, match="job -1 failed"):
        in_processes(square_in_a_process, {k: (k,) for k in (2, -1, 3, 4)}, 2)


def marked_job(folder: str, k: int, seconds: float) -> int:
    """Writes started-k (its pid), then waits; SIGTERM stops it as it stops a training (after
    writing stopped-k)."""
    import signal
    import time
    from pathlib import Path

    def stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, stop)
    Path(folder, f"started-{k}").write_text(str(os.getpid()))
    try:
        time.sleep(seconds)
    except KeyboardInterrupt:
        Path(folder, f"stopped-{k}").write_text("")
        raise
    return k


def _pipeline(folder, jobs: int, seconds: float):
    """A process running in_processes(marked_job) with 2 workers, once both first jobs started."""
    import subprocess
    import sys
    import time
    from pathlib import Path
    root = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), str(root.parent)])}
    code = (f"from pipelines.common import in_processes\nfrom test_pipelines_in_processes import marked_job\n"
            f"in_processes(marked_job, {{k: ({str(folder)!r}, k, {seconds}) for k in range({jobs})}}, 2)")
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while len(list(Path(folder).glob("started-*"))) < 2:
        assert time.monotonic() - t0 < 300 and proc.poll() is None   # spawned workers import torch: slow on a busy machine
        time.sleep(0.05)
    return proc


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is gone too
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(os.name != "posix", reason="signals between processes")
def test_sigterm_to_the_pipeline_stops_its_running_jobs_and_starts_no_other(tmp_path):
    import signal
    import time
    proc = _pipeline(tmp_path, jobs=6, seconds=30)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=20) != 0                     # not 30 s of the running jobs, nor the rest
    time.sleep(0.5)
    started = sorted(p.name.removeprefix("started-") for p in tmp_path.glob("started-*"))
    assert len(started) == 2 and sorted(p.name.removeprefix("stopped-") for p in tmp_path.glob("stopped-*")) == started
    assert not any(_alive(int(p.read_text())) for p in tmp_path.glob("started-*"))


@pytest.mark.skipif(os.name != "posix", reason="signals between processes")
def test_workers_of_a_killed_pipeline_stop_their_jobs_start_no_other_and_end(tmp_path):
    import signal
    import time
    from pipelines.common import ORPHAN_GRACE
    proc = _pipeline(tmp_path, jobs=4, seconds=30)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    pids = [int(p.read_text()) for p in tmp_path.glob("started-*")]
    try:
        t0 = time.monotonic()
        while any(map(_alive, pids)) and time.monotonic() - t0 < ORPHAN_GRACE + 10:
            time.sleep(0.2)
        assert not any(map(_alive, pids))             # not the 30 s of their jobs, nor waiting for more
        started = sorted(p.name.removeprefix("started-") for p in tmp_path.glob("started-*"))
        # stopped as a training stops (SIGTERM), and the job the pool had handed a worker ahead refused
        assert len(started) == 2 and sorted(p.name.removeprefix("stopped-") for p in tmp_path.glob("stopped-*")) == started
    finally:
        for pid in pids:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_sigterm_in_any_stage_ends_the_pipeline_with_its_message(capsys):
    """Not only while in_processes runs: a data stage stopped by SIGTERM says so too."""
    import signal
    import time
    from pipelines.common import guarded

    def stage():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(10)                      # the signal ends it long before
    before = signal.getsignal(signal.SIGTERM)
    assert guarded(stage) == 130
    assert "error: interrupted: SIGTERM; rerun the same command to go on" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) == before
