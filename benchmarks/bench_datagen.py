"""Generation speed: `datagen` against bare PyBullet stepping of the same scenes, and worker scaling.

    python benchmarks/bench_datagen.py [--scenes 400] [--objects 1] [--repeats 3]

Bare PyBullet = build the same world (fresh client, same settings) and step it for the same
duration, without recording or writing. Last, `datagen toss` as a user runs it (a fresh
process, 1 worker, start-up included), with and without glibc's default heap behaviour
(DATAGEN_KEEP_HEAP=0: freed memory handed back to the system after a scene and faulted in again
by the next, datagen.toss.keep_freed_memory); in-process timings cannot show that saving,
because how much is handed back depends on what the process allocated before. `datagen` = scene sampling, simulation, recording and
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

from datagen.scenes import load_config  # noqa: E402
from datagen.toss import generate  # noqa: E402
from datagen.scenes import sample_scene  # noqa: E402
from datagen.toss import build_world, pb, steps_per_frame  # noqa: E402


def step_only(spec, cfg: dict) -> None:
    """Build and step the same world as datagen.toss.simulate without recording: the bare-PyBullet
    baseline (here and in bench_learned_vs_physics.py, bench_multi_object.py)."""
    frames, sub = int(cfg["scene"]["frames"]), steps_per_frame(cfg)
    c, _ = build_world(spec, cfg)
    try:
        for _ in range((frames - 1) * sub):
            pb.stepSimulation(physicsClientId=c)
    finally:
        pb.disconnect(c)


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

    def cli(keep_heap: str):
        def run():
            import subprocess
            with tempfile.TemporaryDirectory() as d:
                subprocess.run([sys.executable, "-m", "datagen.cli", "toss", "--out", str(Path(d) / "ds"), "--scenes",
                                str(a.scenes), "--objects", a.objects, "--workers", "1", "--quiet"],
                               env={**os.environ, "DATAGEN_KEEP_HEAP": keep_heap}, check=True, stdout=subprocess.DEVNULL)
        return run

    t_bare = best_of(a.repeats, bare)
    t_one = best_of(a.repeats, datagen(1))
    t_two = best_of(a.repeats, datagen(2))
    frames = cfg["scene"]["frames"]
    print(f"{a.scenes} scenes x {frames} frames, objects {a.objects}, {os.cpu_count()} cores, best of {a.repeats}")
    print(f"{'what':<34}{'seconds':>9}{'traj/s':>10}{'ratio':>8}")
    t_cli_kept, t_cli_given = best_of(a.repeats, cli("1")), best_of(a.repeats, cli("0"))
    rows = [("bare PyBullet (build + step)", t_bare, 1.0),
            ("datagen, 1 worker", t_one, t_one / t_bare),
            ("datagen, 2 workers", t_two, t_two / t_bare),
            ("datagen toss (CLI, 1 worker)", t_cli_kept, t_cli_kept / t_bare),
            ("datagen toss, heap given back", t_cli_given, t_cli_given / t_bare)]
    for name, t, r in rows:
        print(f"{name:<34}{t:9.2f}{a.scenes / t:10.1f}{r:8.2f}x")
    print(f"overhead of datagen over bare PyBullet (1 worker): {t_one / t_bare:.2f}x")
    print(f"speed-up of 2 workers over 1: {t_one / t_two:.2f}x")
    print(f"keeping freed heap memory (datagen.toss.keep_freed_memory): datagen toss {t_cli_given / t_cli_kept:.2f}x "
          "as fast as with glibc's defaults")


if __name__ == "__main__":
    main()
