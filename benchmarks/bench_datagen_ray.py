"""The Ray backend against the process pool on one machine, and what starting Ray costs.

    python benchmarks/bench_datagen_ray.py [--scenes 200] [--workers 2] [--repeats 3]

Rows: `ray.init` of a local cluster of --workers CPUs (and its shutdown); `datagen` with the
process pool; with `--backend ray` as the command runs it (a local cluster started and stopped
inside); and with Ray already running (what a long-lived cluster costs per dataset). Best of
--repeats. The outputs are checked to be byte-identical.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from datagen.scenes import load_config  # noqa: E402
from datagen.toss import generate  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_datagen import best_of  # noqa: E402


def main(argv=None):
    import logging

    import ray
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=200)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--scenes-per-shard", type=int, default=25)
    a = p.parse_args(argv)
    cfg = load_config()
    tmp = Path(tempfile.mkdtemp(prefix="bench-ray-"))
    n = {"i": 0}

    def datagen(backend):
        def run():
            n["i"] += 1
            generate(cfg, 0, {"train": a.scenes}, tmp / f"{backend}-{n['i']}", workers=a.workers,
                     per_shard=a.scenes_per_shard, progress=False, backend=backend)
        return run

    inits, shutdowns = [], []
    for _ in range(a.repeats):
        t = time.perf_counter()
        ray.init(num_cpus=a.workers, include_dashboard=False, logging_level=logging.WARNING)
        inits.append(time.perf_counter() - t)
        t = time.perf_counter()
        ray.shutdown()
        shutdowns.append(time.perf_counter() - t)
    t_pool = best_of(a.repeats, datagen("process"))
    t_ray = best_of(a.repeats, datagen("ray"))
    ray.init(num_cpus=a.workers, include_dashboard=False, logging_level=logging.WARNING)
    datagen("ray")()      # warm the workers: a running cluster has them
    t_warm = best_of(a.repeats, datagen("ray"))
    ray.shutdown()
    outs = sorted(tmp.iterdir())
    ref = {f.name: f.read_bytes() for f in outs[0].iterdir()}
    same = all({f.name: f.read_bytes() for f in o.iterdir()} == ref for o in outs)
    print(f"{a.scenes} scenes x {cfg['scene']['frames']} frames, {a.scenes_per_shard} a shard, {a.workers} workers, "
          f"{os.cpu_count()} cores, best of {a.repeats}; load average {os.getloadavg()[0]:.1f}")
    print(f"ray.init (local, {a.workers} CPUs): best {min(inits):.2f} s, worst {max(inits):.2f} s; "
          f"ray.shutdown {min(shutdowns):.2f} s")
    for name, t in (("process pool", t_pool), ("ray, started and stopped by the command", t_ray),
                    ("ray, cluster already running", t_warm)):
        print(f"{name:<42}{t:8.2f} s{a.scenes / t:9.1f} scenes/s")
    print(f"all outputs byte-identical: {same}")
    import shutil
    shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
