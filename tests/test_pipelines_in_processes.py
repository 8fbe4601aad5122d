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
