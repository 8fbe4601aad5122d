"""Generation speed: `datagen` against bare PyBullet stepping of the same scenes, and worker scaling.

    python benchmarks/bench_datagen.py [--scenes 400] [--objects 1] [--repeats 3]

Bare PyBullet = build the same world (fresh client, same settings) and step it for the same
duration, without recording or writing; it is timed again in a fresh process with glibc's
default heap behaviour (DATAGEN_KEEP_HEAP=0, freed memory handed back to the system after
every scene: datagen.simulate.keep_freed_memory), the "before" of that saving. `datagen` = scene sampling, simulation, recording and
HDF5 writing, as `datagen toss` runs them. All figures come from this one run; the best of
--repeats is taken to damp noise from other processes.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from datagen.config import load_config  # noqa: E402
from datagen.generate import generate  # noqa: E402
from datagen.scenes import sample_scene  # noqa: E402
from datagen.simulate import step_only  # noqa: E402


def best_of(repeats, fn):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=400)
    p.add_argument("--objects", default="1", help="objects per scene, e.g. 1 or 3-10")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--scenes-per-shard", type=int, default=50)
    p.add_argument("--bare-only", action="store_true", help=argparse.SUPPRESS)  # the subprocess's job
    a = p.parse_args(argv)
    cfg = load_config(sets=[f'scene.objects="{a.objects}"'])
    specs = [sample_scene(cfg, 0, "train", i) for i in range(a.scenes)]

    def bare():
        for s in specs:
            step_only(s, cfg)

    def datagen(workers):
        def run():
            with tempfile.TemporaryDirectory() as d:
                generate(cfg, 0, {"train": a.scenes}, Path(d) / "ds", workers=workers,
                         per_shard=a.scenes_per_shard, progress=False)
        return run

    if a.bare_only:
        print(best_of(a.repeats, bare))
        return
    import subprocess
    before = subprocess.run([sys.executable, __file__, "--bare-only", "--scenes", str(a.scenes), "--objects", a.objects,
                             "--repeats", str(a.repeats)], env={**os.environ, "DATAGEN_KEEP_HEAP": "0"},
                            capture_output=True, text=True, check=True)
    t_default_heap = float(before.stdout.strip().splitlines()[-1])
    t_bare = best_of(a.repeats, bare)
    t_one = best_of(a.repeats, datagen(1))
    t_two = best_of(a.repeats, datagen(2))
    frames = cfg["scene"]["frames"]
    print(f"{a.scenes} scenes x {frames} frames, objects {a.objects}, {os.cpu_count()} cores, best of {a.repeats}")
    print(f"{'what':<34}{'seconds':>9}{'traj/s':>10}{'ratio':>8}")
    rows = [("bare PyBullet, heap given back", t_default_heap, t_default_heap / t_bare),
            ("bare PyBullet (build + step)", t_bare, 1.0),
            ("datagen, 1 worker", t_one, t_one / t_bare),
            ("datagen, 2 workers", t_two, t_two / t_bare)]
    for name, t, r in rows:
        print(f"{name:<34}{t:9.2f}{a.scenes / t:10.1f}{r:8.2f}x")
    print(f"overhead of datagen over bare PyBullet (1 worker): {t_one / t_bare:.2f}x")
    print(f"speed-up of 2 workers over 1: {t_one / t_two:.2f}x")
    print(f"keeping freed heap memory (datagen.simulate.keep_freed_memory): {t_default_heap / t_bare:.2f}x "
          "faster bare PyBullet")


if __name__ == "__main__":
    main()
