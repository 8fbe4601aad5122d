"""`datagen toss --backend ray`: each shard a Ray task, on a local cluster or one at --ray-address.

Imported only when that backend is asked for, so the process pool's path does not carry it."""
from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from pathlib import Path

from plumbing import ConfigError, DataError

from .output import ShardTask, commit_shard
from .toss import build_task
from .shards import write_error


def require_ray():
    """The ray module, or one line naming the extra (checked before anything is written)."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--backend ray needs Ray: pip install 'rigid-gns[ray]'") from None
    return ray


# How long a Ray cluster at --ray-address may take to answer before the run gives up (seconds):
# ray.init itself retries an address where nothing listens for minutes.
RAY_CONNECT_TIMEOUT = float(os.environ.get("DATAGEN_RAY_CONNECT_TIMEOUT", "15"))


def _probe(address: str, timeout: float) -> None:
    """Refuse at once a host:port (or ray://host:port) where nothing accepts a connection."""
    import socket
    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        return                          # "auto", "local" and such: ray.init decides
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        why = "timed out" if isinstance(e, socket.timeout) else (e.strerror or type(e).__name__)
        raise DataError(f"cannot reach the Ray cluster at {address}: nothing answers at {hostport} ({why})") from None


def _answers_within(address: str, timeout: float) -> None:
    """Refuse a cluster that does not let a Ray client connect within `timeout` seconds.

    Tried in a child process: ray.init blocks in C++ where no signal reaches it, and started
    from another thread it fails, so a child, killed at the deadline, is the one bounded wait."""
    import subprocess
    code = ("import logging, ray; ray.init(address=%r, logging_level=logging.ERROR, log_to_driver=False); "
            "ray.shutdown()" % address)
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise DataError(f"cannot reach the Ray cluster at {address}: no answer within {timeout:g} s "
                        "(DATAGEN_RAY_CONNECT_TIMEOUT)") from None
    if r.returncode:
        lines = [ln.strip() for ln in r.stderr.splitlines() if ln.strip()]
        raise DataError(f"cannot reach the Ray cluster at {address}: {lines[-1] if lines else 'ray.init failed'}")


@contextmanager
def ray_cluster(workers: int, address: str | None, timeout: float | None = None):
    """The ray module, connected to the cluster at `address` (or RAY_ADDRESS) or to a local
    cluster of `workers` CPUs started here and stopped afterwards. Entered before the output
    folder is touched, so a cluster that does not answer leaves nothing behind."""
    ray = require_ray()
    import logging
    address = address or os.environ.get("RAY_ADDRESS") or None
    timeout = RAY_CONNECT_TIMEOUT if timeout is None else timeout
    started = not ray.is_initialized()
    if started:
        where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
        try:
            if address:
                _probe(address, timeout)
                _answers_within(address, timeout)
                ray.init(address=address, logging_level=logging.WARNING)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING)
        except DataError:
            raise
        except Exception as e:  # ray raises ConnectionError, RuntimeError, ValueError... for a bad address
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise DataError(f"cannot start or reach {where}: {first}") from None
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def ray_tasks(ray, jobs: list[ShardTask], cfg: dict, seed: int, out: Path, planned: dict):
    """Run shards as Ray tasks, yielding (name, count, tunnelled ids) as each is written.

    A task returns its shard's bytes and the driver writes them, so the cluster's nodes need no
    shared file system with --out."""
    remote = ray.remote(num_cpus=1)(build_task)  # retried if a node dies: a shard is a pure function of its task
    cfg_ref = ray.put(cfg)
    pending = {remote.remote(t, cfg_ref, seed): t for t in jobs}
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        task = pending.pop(done[0])
        try:
            image, bad = ray.get(done[0])
        except ray.exceptions.RayTaskError as e:
            cause = getattr(e, "cause", None)
            if isinstance(cause, (DataError, ConfigError)):
                raise cause from None
            if isinstance(cause, OSError):
                raise write_error(out / task.name, cause) from None
            raise DataError(f"ray task for {task.name} failed: {type(cause or e).__name__}: "
                            f"{str(cause or e).splitlines()[0] if str(cause or e) else ''}") from None
        commit_shard(out, planned, task.name, image)
        yield task.name, task.count, bad
