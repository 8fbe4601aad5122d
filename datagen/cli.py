"""`datagen`: make toss datasets (`toss`), check them (`inspect`), import real tosses (`import`)."""
from __future__ import annotations

import argparse
import sys

from plumbing import ConfigError
from .scenes import load_config
from plumbing import version_line

EPILOG = """examples:
  datagen toss --shapes cube,sphere --sizes small --materials metal --scenes 100 --out data/toy
  datagen toss --objects 3-10 --scenes 50 --valid 10 --test 10 --workers 2 --seed 1 --out data/multi
  datagen inspect data/toy
  datagen toss --scenes 1000 --backend ray --workers 8 --out data/big
  datagen toss --engine mujoco --stiffness soft --scenes 1000 --test 100 --out data/cubes_soft
  datagen toss --scenes 1000 --shard-index $SLURM_ARRAY_TASK_ID --num-shards 10 --out data/big   # one of 10 runs
"""


def _fail(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


def cmd_toss_mujoco(a) -> int:
    """--engine mujoco: one real-cube-like cube a toss (datagen/mujoco_tosses.py, configs/mujoco_cubes.toml)."""
    from .mujoco_tosses import generate_tosses, load_config as load_mujoco_config
    movi_only = [f"--{k.replace('_', '-')}" for k in ("shapes", "sizes", "materials", "objects", "physics_rate", "backend",
                                                      "shard_index", "num_shards", "ray_address", "resume")
                 if getattr(a, k) not in (None, False, "process")]
    if movi_only:
        raise ConfigError(f"{', '.join(movi_only)}: MOVi-A options, not for --engine mujoco")
    sets = list(a.set or []) + [f"scene.{k}={v}" for k, v in (("frames", a.frames), ("frame_rate", a.frame_rate))
                                if v is not None]
    cfg = load_mujoco_config(a.config, sets, a.stiffness)
    meta = generate_tosses(cfg, a.seed, {"train": a.scenes, "valid": a.valid, "test": a.test}, a.out,
                           overwrite=a.overwrite, progress=not a.quiet, workers=a.workers)
    print(f"wrote {sum(v['num_scenes'] for v in meta['splits'].values())} MuJoCo tosses ({cfg['contact']['stiffness']}: "
          f"solref timeconst {cfg['contact']['timeconst']:g} s) to {a.out}, fingerprint {meta['fingerprint'][:16]}")
    return 0


def cmd_toss(a) -> int:
    if a.engine == "mujoco":
        return cmd_toss_mujoco(a)
    if a.stiffness is not None:
        raise ConfigError("--stiffness is MuJoCo's contact stiffness: give --engine mujoco")
    from .toss import generate
    sets = list(a.set or [])
    for flag, key in (("shapes", "scene.shapes"), ("sizes", "scene.sizes"), ("materials", "scene.materials")):
        val = getattr(a, flag)
        if val is not None:
            items = [s.strip() for s in val.split(",") if s.strip()]
            sets.append(f"{key}=[{', '.join(repr(s).replace(chr(39), chr(34)) for s in items)}]")
    for flag, key in (("objects", "scene.objects"), ("frames", "scene.frames"), ("frame_rate", "scene.frame_rate"),
                      ("physics_rate", "physics.rate")):
        val = getattr(a, flag)
        if val is not None:
            sets.append(f'{key}="{val}"' if flag == "objects" else f"{key}={val}")
    cfg = load_config(a.config, sets)
    counts = {"train": a.scenes, "valid": a.valid, "test": a.test}
    meta = generate(cfg, a.seed, counts, a.out, workers=a.workers, per_shard=a.scenes_per_shard,
                    resume=a.resume, overwrite=a.overwrite, progress=not a.quiet, backend=a.backend,
                    shard_index=a.shard_index, num_shards=a.num_shards, ray_address=a.ray_address)
    n = sum(v["num_scenes"] for v in meta["splits"].values())
    if not meta["complete"]:
        from pathlib import Path
        names = [name for v in meta["splits"].values() for name in v["shards"]]
        missing = sum(not (Path(a.out) / name).exists() for name in names)
        print(f"wrote part {a.shard_index} of {a.num_shards} to {a.out}; {missing} of {len(names)} shards are still "
              f"missing (other parts): the run that writes the last one completes metadata.json")
        return 0
    print(f"wrote {n} scenes to {a.out} (" + ", ".join(f"{k} {v['num_scenes']}" for k, v in meta["splits"].items()) + ")"
          f", fingerprint {meta['fingerprint'][:16]}")
    return 0


CHANGED = 3   # datagen inspect's exit code for valid shards changed since they were written


def cmd_inspect(a) -> int:
    from .inspect import format_summary, inspect
    problems, summary = inspect(a.path)
    if summary:
        print(format_summary(summary))
    for p in problems:
        print(f"problem: {p}", file=sys.stderr)
    if problems:
        print(f"{len(problems)} problem(s) found in {a.path}", file=sys.stderr)
        return 1
    changed = summary.get("changed_shards") or []
    if changed:
        # Valid data, but not the data its fingerprint (and every run that recorded it) describes.
        print(f"changed: {len(changed)} shard(s) differ from the checksums recorded when they were written "
              f"({', '.join(changed[:5])}); the fingerprint no longer describes the data", file=sys.stderr)
        return CHANGED
    print("ok: no problems found")
    return 0


def cmd_import(a) -> int:
    from .contactnets import import_contactnets
    meta = import_contactnets(a.src, a.out, overwrite=a.overwrite, progress=not a.quiet,
                              allow_pickle=a.allow_pickle)
    print(f"imported {sum(v['num_scenes'] for v in meta['splits'].values())} tosses into {a.out}")
    return 0


def cmd_import_kubric(a) -> int:
    from .kubric import import_kubric
    meta = import_kubric(a.src, a.out, split=a.split, frame_rate=a.frame_rate, cube_as=a.cube_as,
                         overwrite=a.overwrite, progress=not a.quiet)
    print(f"imported {meta['splits'][a.split]['num_scenes']} Kubric scenes into {a.out} ({a.split} split)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="datagen", description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=version_line())
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("toss", help="simulate tossed objects in PyBullet (or a cube in MuJoCo) and write HDF5 shards",
                       description="Simulate MOVi-A-style tosses (configs/movi_a.toml), or with --engine mujoco "
                                   "real-cube-like tosses (configs/mujoco_cubes.toml), and write a dataset "
                                   "folder: shards per split plus metadata.json (docs/data_format.md).")
    t.add_argument("--out", required=True, help="output dataset folder")
    t.add_argument("--engine", choices=("pybullet", "mujoco"), default="pybullet",
                   help="pybullet: MOVi-A scenes (default); mujoco: one cube tossed like the real ContactNets cube, "
                        "configs/mujoco_cubes.toml (the `mujoco` extra)")
    t.add_argument("--stiffness", help="--engine mujoco: contact stiffness hard, medium or soft (solref time "
                                       "constants 0.02, 0.0577, 0.1 s; default hard)")
    t.add_argument("--scenes", type=int, default=100, help="training scenes (default 100)")
    t.add_argument("--valid", type=int, default=0, help="validation scenes (default 0)")
    t.add_argument("--test", type=int, default=0, help="test scenes (default 0)")
    t.add_argument("--seed", type=int, default=0, help="master seed; each scene's RNG is keyed by (seed, split, index)")
    t.add_argument("--workers", type=int, default=1, help="worker processes; the output does not depend on it")
    t.add_argument("--shapes", help="comma list of cube, beveled_cube, cylinder, sphere")
    t.add_argument("--sizes", help="comma list of size names from the config (small, large)")
    t.add_argument("--materials", help="comma list of material names from the config (metal, rubber)")
    t.add_argument("--objects", help="objects per scene: N, a range like 3-10, or a comma list of them (1,3-10: half the scenes one object, half 3-10; default 1)")
    t.add_argument("--frames", type=int, help="frames recorded per scene (default 24)")
    t.add_argument("--frame-rate", type=float, help="recorded frames per second (default 12)")
    t.add_argument("--physics-rate", type=float, help="physics steps per second (default 240)")
    t.add_argument("--config", help="a TOML file overriding the movi_a preset (configs/movi_a.toml; with --engine "
                                    "mujoco configs/mujoco_cubes.toml)")
    t.add_argument("--set", action="extend", nargs="+", metavar="KEY=VALUE",
                   help="override config keys, typed as in the preset, e.g. --set floor.friction=0.5 physics.ccd=true")
    t.add_argument("--scenes-per-shard", type=int, default=50, help="scenes per HDF5 shard (default 50)")
    t.add_argument("--backend", choices=("process", "ray"), default="process",
                   help="process: a pool of --workers processes (default); ray: Ray tasks, on a local cluster of "
                        "--workers CPUs or the cluster at --ray-address / RAY_ADDRESS (the `ray` extra)")
    t.add_argument("--ray-address", metavar="ADDR", help="with --backend ray: an existing cluster (e.g. auto, ray://host:10001)")
    t.add_argument("--shard-index", type=int, metavar="I",
                   help="with --num-shards K: write only shards whose number in the plan (train, valid, test "
                        "shards in order) modulo K is I; K such runs into one --out make the whole dataset")
    t.add_argument("--num-shards", type=int, metavar="K", help="number of runs the shards are divided among (see --shard-index)")
    g = t.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true", help="finish an interrupted run in --out (same command)")
    g.add_argument("--overwrite", action="store_true", help="replace an existing dataset in --out")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=cmd_toss)
    i = sub.add_parser("inspect", help="validate a dataset folder and print a summary",
                       description="Check schema version, array shapes, NaN/inf, unit quaternions, objects "
                                   "below the floor, missing or truncated shards. Exit 1 if any problem, 3 if "
                                   "the data is valid but shards changed since they were written (the "
                                   "fingerprint no longer describes them), 0 otherwise.")
    i.add_argument("path")
    i.set_defaults(func=cmd_inspect)
    m = sub.add_parser("import", help="import external data into the shard format")
    msub = m.add_subparsers(dest="source", required=True)
    c = msub.add_parser("contactnets", help="real cube tosses from DAIRLab/contact-nets data/tosses_processed")
    c.add_argument("src", help="folder of N.pt toss files (tosses_processed)")
    c.add_argument("--out", required=True)
    c.add_argument("--overwrite", action="store_true", help="replace a dataset in --out")
    c.add_argument("--allow-pickle", action="store_true",
                   help="read toss files holding more than tensors (runs their pickle code: trusted files only)")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_import)
    k = msub.add_parser("kubric", help="MOVi-A records: Kubric scene folders (metadata.json) or TFDS examples as .npz",
                        description="Import Kubric's MOVi-A records (datagen/kubric.py says which layouts and keys) "
                                    "into one split, to score a model on them with gns eval.")
    k.add_argument("src", help="folder of Kubric scene folders (each with metadata.json) and/or .npz TFDS examples")
    k.add_argument("--out", required=True)
    k.add_argument("--split", choices=("train", "valid", "test"), default="test", help="the split they go to (default test)")
    k.add_argument("--frame-rate", type=float, help="frames a second, for .npz examples (TFDS holds none; default 12)")
    k.add_argument("--cube-as", default="beveled_cube", help="our shape for Kubric's cube: beveled_cube (default) or cube")
    k.add_argument("--overwrite", action="store_true", help="replace a dataset in --out")
    k.add_argument("--quiet", action="store_true")
    k.set_defaults(func=cmd_import_kubric)
    return p


def main(argv=None) -> int:
    from plumbing import DataError
    a = build_parser().parse_args(argv)
    from plumbing import sigterm_as_interrupt
    try:
        with sigterm_as_interrupt():     # the workers are stopped and the message says what was kept
            return a.func(a)
    except (ConfigError, DataError) as e:
        return _fail(str(e))
    except KeyboardInterrupt:
        if getattr(a, "engine", None) == "mujoco":
            return _fail("interrupted; its shards were removed (rerun the same command)")
        return _fail("interrupted; no partial shard was left (rerun with --resume to finish)")
    except OSError as e:
        return _fail(f"{e.strerror or e} ({e.filename})" if getattr(e, "filename", None) else str(e))


if __name__ == "__main__":
    sys.exit(main())
