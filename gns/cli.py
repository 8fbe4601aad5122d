"""`gns` command line: one function per subcommand, registered on argparse subparsers.

A user error (bad data folder, unknown config key, unusable checkpoint, NaN loss) prints one
line `error: ...` on stderr and exits with status 2 (bad input) or 1 (training failed).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import warnings

from plumbing import DataError
from gns.config import ConfigError

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


def cmd_train(args: argparse.Namespace) -> None:
    from gns.run_folder import resolve_config, world_from_env
    from gns.train import train

    flags = {"steps": args.steps, "device": args.device, "autocast": args.autocast,
             "tensorboard": "true" if args.tensorboard else None, "compile": "true" if args.compile else None}
    overrides = list(args.set or []) + [f"train.{k}={v}" for k, v in flags.items() if v is not None]
    cfg = resolve_config(args.out, args.resume, args.config, overrides)
    step = train(args.data, args.out, cfg, resume=args.resume, overwrite=args.overwrite)
    if world_from_env().main:
        print(f"done at step {step}; checkpoints and metrics.jsonl in {args.out}")


def add_train_parser(sub) -> None:
    p = sub.add_parser("train", help="train a graph network simulator on a dataset folder",
                       description="Train a GNS on the train split of DIR; validate on its valid split.")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (metadata.json + shards)")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder for checkpoints and metrics.jsonl")
    p.add_argument("--config", metavar="TOML", help="a TOML file or a shipped preset by name: gns_tiny, gns_cpu, gns_paper "
                   "(default: built-in, the paper's model)")
    p.add_argument("--steps", type=int, metavar="N", help="train until step N (same as --set train.steps=N)")
    p.add_argument("--set", action="extend", nargs="+", metavar="KEY=VALUE",
                   help="override a config key, e.g. --set model.latent_size=64 train.batch_size=4")
    p.add_argument("--tensorboard", action="store_true",
                   help="also log to TensorBoard event files in RUN/tb (same as --set train.tensorboard=true; "
                        "needs the tensorboard extra)")
    p.add_argument("--device", metavar="DEV", help="cpu, cuda or cuda:N (same as --set train.device=DEV); "
                   "under torchrun each process takes cuda:LOCAL_RANK")
    p.add_argument("--autocast", choices=["none", "bf16", "auto"],
                   help="run the network (only) under bfloat16 autocast (same as --set train.autocast=...); auto: "
                        "where a matrix product of the network's shape measures faster in bf16 on this machine")
    p.add_argument("--compile", action="store_true",
                   help="run the network through torch.compile (same as --set train.compile=true; needs a C++ "
                        "compiler; the first steps compile, tens of seconds)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue from RUN/latest.pt")
    mode.add_argument("--overwrite", action="store_true", help="delete RUN's checkpoints and start again")
    p.set_defaults(run=cmd_train)


def _threads(n: int) -> None:
    import torch
    if n < 1:
        raise ConfigError(f"--threads must be >= 1, got {n}")
    # One thread by default: rollouts of small graphs gain little from a second, and with another
    # process on the second core OpenMP barrier waits made 2 threads ~50x slower (measured).
    torch.set_num_threads(n)


def cmd_rollout(args: argparse.Namespace) -> None:
    from gns.rollout_dataset import rollout_run

    _threads(args.threads)
    options = _rollout_options(args)
    done, written, seconds, warmup = rollout_run(args.run_dir, args.data, args.out, args.split, args.limit, options,
                                                 args.device, args.overwrite, _at_data_rate(args), args.between)
    print(f"rolled out {done} scenes in {seconds:.2f} s"
          + (f" (after {warmup:.1f} s compiling, not counted)" if warmup is not None else "")
          + f"; wrote {written} to {args.out}")


def cmd_eval(args: argparse.Namespace) -> None:
    from gns.evaluate import evaluate_run, write_json
    from gns.metrics import format_table
    from plumbing import check_json_output

    _threads(args.threads)
    if args.json:
        check_json_output(args.json, "position_error_pct", "gns eval")
    results, *_ = evaluate_run(args.run_dir, args.data, args.split, args.limit, _rollout_options(args),
                               plots_dir=args.plots, at_data_rate=_at_data_rate(args), device=args.device,
                               protocol=args.protocol, between=args.between)
    print(format_table(results))
    print(f"rollouts: {results['wall_seconds_per_simulated_second']:.3g} s of wall clock per simulated second "
          f"per scene, {results['num_scenes']} scenes batched"
          + (f" (after {results['warmup_seconds']:.1f} s compiling on a first batch, not counted)"
             if results.get("warmup_seconds") is not None else "")
          + (f"; --autocast auto measured and took {'bf16' if results['autocast_used'] == 'bf16' else 'float32'}"
             if results["autocast"] == "auto" else ""))
    c = results.get("object_steps") or {}
    if c.get("object_steps"):
        print(f"object-steps through the network: {c['network']} of {c['object_steps']} "
              f"({100 * c['network'] / c['object_steps']:.1f}%; free flight {c['free_flight']}, asleep {c['asleep']})")
    if args.json:
        summary = {k: v for k, v in results.items() if k != "per_scene"}
        try:
            write_json(args.json, summary)
        except OSError as e:  # checked before the rollouts, but a disk can fill during them: keep the work
            import tempfile
            fd, spare = tempfile.mkstemp(prefix="gns-eval-", suffix=".json")
            os.close(fd)
            write_json(spare, summary)
            print(f"error: cannot write {args.json} ({e.strerror or e}); the results are in {spare}", file=sys.stderr)
            raise SystemExit(EXIT_FAILED)
        print(f"wrote {args.json}")
    if args.plots:
        print(f"plots in {args.plots}")


def _at_data_rate(args: argparse.Namespace) -> bool:
    """--at-data-rate as given, else as a zoo model's card says it was scored (its [eval] table)."""
    if args.at_data_rate is not None:
        return args.at_data_rate
    from gns.checkpoint import is_name
    if is_name(args.run_dir):
        from gns import zoo
        if args.run_dir in zoo.names():
            return bool(zoo.card(args.run_dir).data.get("eval", {}).get("at_data_rate", False))
    return False


# the RolloutOptions fields the rollout flags set (dest = field name); an unset flag is None
OPTION_FLAGS = ("shape_matching", "symmetrize", "body_frames", "free_flight", "free_clearance", "sleep",
                "sleep_fraction", "keep_apart", "autocast", "compile", "batch", "ensemble")


def _rollout_options(args: argparse.Namespace):
    """The model's default options (a zoo model's scored ones, gns.checkpoint.default_options) with the
    flags given on top."""
    from gns.checkpoint import default_options
    check_flags(**{k: getattr(args, k) for k in ("batch", "limit", "sleep_fraction", "free_clearance")})
    given = {k: getattr(args, k) for k in OPTION_FLAGS}
    if given["ensemble"] is not None:
        given["ensemble"] = tuple(given["ensemble"])
    options = default_options(args.run_dir).replace(**given)
    if args.free_clearance is not None and not options.free_flight:
        raise ConfigError("--free-clearance sets free flight's height: it needs --free-flight")
    if args.sleep_fraction is not None and not options.sleep:
        raise ConfigError("--sleep-fraction sets when an object is at rest: it needs --sleep")
    return options


def check_flags(**flags) -> None:
    """Numeric rollout flags (`gns rollout`, `gns eval`) out of range ({dest: value}, None when
    unset): one line naming the flag, before the model or the data are read."""
    rules = {"batch": (lambda v: v >= 1, "a whole number >= 1"), "limit": (lambda v: v >= 1, ">= 1 scene"),
             "sleep_fraction": (lambda v: math.isfinite(v) and v > 0, "a finite number > 0"),
             "free_clearance": (lambda v: math.isfinite(v) and v >= 0, "a finite height >= 0 above the floor")}
    for dest, value in flags.items():
        ok, want = rules[dest]
        if value is not None and not ok(value):
            raise DataError(f"--{dest.replace('_', '-')} must be {want}, got {value:g}")


def _add_rollout_args(p) -> None:
    p.add_argument("--run", required=True, dest="run_dir", metavar="RUN",
                   help="a zoo model by name (gns models lists them), a run folder (its latest.pt) or a .pt checkpoint")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder to roll out")
    p.add_argument("--split", default="test", help="split to roll out (default test)")
    p.add_argument("--limit", type=int, metavar="N", help="only the first N scenes")
    p.add_argument("--threads", type=int, default=1, metavar="T",
                   help="torch threads (default 1: on a shared machine more wait on each other)")
    p.add_argument("--device", default="cpu", metavar="DEV", help="cpu, cuda or cuda:N (default cpu)")
    o = p.add_argument_group("rollout options", "how the model is rolled out (gns.spec.RolloutOptions). "
                             "Unset, each is a zoo model's scored setting (its card's [rollout]), else the default "
                             "given; the options used are recorded in the output as rollout_options")
    # dest = the RolloutOptions field (OPTION_FLAGS); every default None: unset, the model's own stays
    o.add_argument("--batch", type=int, metavar="B",
                   help="object tracks rolled out together (default 1024: the 400 test scenes of MOVi-A in one "
                        "batch, 10-20%% faster than 256, experiments/log.md; smaller if memory is short)")
    o.add_argument("--shape-matching", action=argparse.BooleanOptionalAction,
                   help="project each prediction onto the rigid shape (default); --no-shape-matching feeds raw "
                        "predictions back (the paper's -sm ablation)")
    o.add_argument("--sleep", action=argparse.BooleanOptionalAction,
                   help="hold resting objects still until another object touches them, as physics engines "
                        "deactivate bodies (docs/results.md); off by default")
    # the keys of gns.symmetry.SYMMETRY_GROUPS, written out so that --help does not import torch
    o.add_argument("--symmetrize", nargs="?", const="d2", choices=["none", "d2", "d4", "d1", "c2", "c4"],
                   metavar="GROUP",
                   help="average each step's prediction over the floor's symmetries: d2 (the default when no GROUP "
                        "is given) the mirrors in x and y and the half turn, exactly mirror-equivariant rollouts "
                        "at 4x the network cost; d4 also the quarter turns and diagonal mirrors, at 8x "
                        "(measured 0.2 points better, experiments/log.md); d1 (the mirror in x) and "
                        "c2 (the half turn) at 2x, c4 (the quarter turns) at 4x; none: one network call (default). "
                        "For a model trained with features.canonical_heading (every recent MOVi-A model) d1 "
                        "measured nearly d2's accuracy at half its cost (experiments/log.md)")
    o.add_argument("--keep-apart", action=argparse.BooleanOptionalAction,
                   help="after each step, translate the objects of a scene out of each other where a vertex of "
                        "one entered another (a projection, as shape matching is; exact for convex meshes); "
                        "off by default, no effect on scenes of one object")
    o.add_argument("--body-frames", action=argparse.BooleanOptionalAction,
                   help="also average over each object's equivalent body frames (a cube's 24 rotations onto "
                        "itself): exactly invariant to which one describes it, at that many times the cost")
    o.add_argument("--autocast", choices=["none", "bf16", "auto"],
                   help="run the network (only) under bfloat16 autocast, accuracy measured unchanged: 1.6-2.8x "
                        "faster rollouts on an AMD EPYC with avx512_bf16, but 1.8x slower matrix products on an "
                        "Intel Xeon with avx512_bf16 and no AMX; auto: bf16 where a matrix product of the network's "
                        "shape measures faster on this machine (benchmarks/bench_learned_vs_physics.py measures "
                        "rollouts); default none")
    o.add_argument("--compile", action=argparse.BooleanOptionalAction,
                   help="run the network through torch.compile with inductor's freezing (the weights as constants, "
                        "laid out once for the CPU's matrix kernels: ~6%% faster rollouts than compiling alone, "
                        "experiments/log.md); the first steps compile, tens of seconds, on a first batch rolled out before "
                        "the timed rollouts and not counted in their wall clock")
    o.add_argument("--free-flight", action=argparse.BooleanOptionalAction,
                   help="objects out of reach of the floor and of other objects follow the exact inertial update "
                        "(gravity, constant spin) instead of the network, which then runs only on the others")
    o.add_argument("--free-clearance", type=float, metavar="D",
                   help="--free-flight: how high above the floor (scene units) every vertex must stay, now and "
                        "after the inertial step, to be in free flight (default: the model's floor clip, beyond "
                        "which its network does not see the floor). Lower takes objects near the floor that "
                        "cannot reach it within the step out of the network too: on MOVi-A 0.5 cut the object-"
                        "steps in the network from 88%% to ~80%%, accuracy level within 0.1 (experiments/log.md)")
    o.add_argument("--ensemble", action="append", metavar="RUN",
                   help="another trained run (same network mesh, floor and time step; e.g. another seed or "
                        "recipe) whose prediction each step averages with the model's; repeat for more members, "
                        "each costs one more network call")
    o.add_argument("--sleep-fraction", type=float, metavar="F",
                   help="--sleep: an object is at rest when no vertex moved F x |g| dt^2 in either input step "
                        "(default 0.1)")


def add_eval_parsers(sub) -> None:
    r = sub.add_parser("rollout", help="roll a trained model out over a dataset and write the trajectories",
                       description="Start every scene from its first 3 true frames and roll out the rest. "
                                   "The output is a dataset folder in docs/data_format.md, readable by the "
                                   "same reader (and by `datagen inspect`).")
    _add_rollout_args(r)
    r.add_argument("--out", required=True, metavar="DIR", help="output folder for the rolled-out dataset")
    r.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    _add_reading_args(r)
    r.set_defaults(run=cmd_rollout)
    e = sub.add_parser("eval", help="roll out and score: position %%, rotation degrees, penetration %%",
                       description="Roll out a split and print the metrics of docs/metrics.md (averaged over "
                                   "frames, then scenes), at fixed horizons and by shape, size and material.")
    _add_rollout_args(e)
    e.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    _add_reading_args(e)
    e.add_argument("--protocol", choices=["240hz"],
                   help="240hz: later MOVi-A work's protocol on scenes recorded at 240 Hz (translation and rotation "
                        "RMSE at 50, 75 and 100 frames after the last given one; implies --at-data-rate)")
    e.add_argument("--plots", metavar="DIR", help="write trajectory plots, error against time and a GIF here")
    e.set_defaults(run=cmd_eval)


def _add_reading_args(p) -> None:
    """--at-data-rate and --between of gns eval and gns rollout."""
    p.add_argument("--at-data-rate", action=argparse.BooleanOptionalAction,
                   help="a model trained at every k-th frame is read at every frame of the data (its poses "
                        "between its steps read as --between says), the instants any other simulator is scored "
                        "at; default: a zoo model as its card's [eval] at_data_rate says, any other at its own frames")
    p.add_argument("--between", choices=["learned", "spline"], default="learned",
                   help="with --at-data-rate, how the frames between the model's steps are read: by the reader "
                        "its file holds (gns export --between; a cubic spline where it holds none), or by the "
                        "spline (default: learned)")


def cmd_export(args: argparse.Namespace) -> None:
    from gns.checkpoint import checkpoint_of
    from gns.zoo import export_model

    contact = None if args.contact is None else checkpoint_of(args.contact)
    out = export_model(checkpoint_of(args.run_dir), args.out, overwrite=args.overwrite, contact=contact,
                       between=args.between)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB): model, config and training ranges, no optimiser state"
          + ("; with its contact network" if contact else "") + ("; with its reader between steps" if args.between else ""))


def add_export_parser(sub) -> None:
    x = sub.add_parser("export", help="write a trained model without optimiser state, to share or ship",
                       description="Copy a run's latest checkpoint without the optimiser and random state: "
                                   "`gns rollout`/`gns eval` read it like a run; training cannot resume from it.")
    x.add_argument("--run", required=True, dest="run_dir", metavar="RUN", help="run folder or .pt checkpoint")
    x.add_argument("--out", required=True, metavar="FILE", help="output .pt file")
    x.add_argument("--overwrite", action="store_true",
                   help="replace an earlier exported model at FILE (never a run's checkpoint or another file)")
    x.add_argument("--contact", metavar="RUN",
                   help="a second model of the same graphs (run folder or .pt) that rolls out the objects "
                        "touching another: a contact network (docs/model.md)")
    x.add_argument("--between", metavar="DATA",
                   help="a model that steps k recorded frames: fit its reader of the frames between its steps "
                        "(gns eval --at-data-rate reads by it) on DATA's train split, recorded at the data's rate")
    x.set_defaults(run=cmd_export)


def cmd_plot_curves(args: argparse.Namespace) -> None:
    from gns.charts import plot_runs

    out, count = plot_runs(args.runs, args.out, log_loss=not args.linear)
    print(f"wrote {out} ({count} run{'s' if count > 1 else ''})")


def add_plot_parser(sub) -> None:
    c = sub.add_parser("plot-curves", help="plot training curves (loss, validation, learning rate) of runs",
                       description="Draw the training and validation loss, the validation rollout error and "
                                   "the learning rate against the step, from each run's metrics.jsonl.")
    c.add_argument("runs", nargs="+", metavar="RUN", help="run folders (or metrics.jsonl files); several are overlaid")
    c.add_argument("--out", required=True, metavar="FILE", help="output image: .png, .pdf or .svg")
    c.add_argument("--linear", action="store_true", help="linear loss axes (default logarithmic)")
    c.set_defaults(run=cmd_plot_curves)


def cmd_models(args: argparse.Namespace) -> None:
    from gns import zoo
    print(zoo.format_card(args.name) if args.name else zoo.format_list())


def add_models_parser(sub) -> None:
    m = sub.add_parser("models", help="list the pretrained models of the zoo, or print one's card",
                       description="The zoo: a few trained models named by purpose. Without NAME, one line "
                                   "each; with NAME, its card: data, the command that retrains it, scores with "
                                   "the exact eval command, speed, limits and the rollout options it was scored "
                                   "with (which gns eval, gns rollout and gns.load use unless told otherwise).")
    m.add_argument("name", nargs="?", metavar="NAME", help="a zoo model's name, e.g. movi_a")
    m.set_defaults(run=cmd_models)


def build_parser() -> argparse.ArgumentParser:
    from plumbing import version_line
    parser = argparse.ArgumentParser(prog="gns", description="Graph network simulator for rigid bodies.")
    parser.add_argument("--version", action="version", version=version_line())
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_train_parser(sub)
    add_eval_parsers(sub)
    add_export_parser(sub)
    add_plot_parser(sub)
    add_models_parser(sub)
    return parser


# Error classes of modules a command may not load, as (module, class): bad input (exit 2), and
# work that ran and failed (exit 1).
BAD_INPUT = (("gns.zoo", "ZooError"),)
FAILED = (("gns.train", "TrainingError"), ("gns.evaluate", "DivergedError"))


def _loaded(names: tuple) -> tuple:
    """The classes of `names` among the modules the command loaded: importing gns.train only to
    name its error would load the training for `gns eval`."""
    return tuple(getattr(sys.modules[m], n) for m, n in names if m in sys.modules)


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    # a warning is one line for a user, not a source location and its code (restored on the way
    # out: a program calling main() keeps its own)
    formatwarning = warnings.formatwarning
    warnings.formatwarning = lambda message, *_args, **_kw: f"warning: {message}\n"
    # Imported after parsing so that `gns --help` and usage errors do not wait for torch.
    from gns.checkpoint import CheckpointError
    from gns.spec import OptionsError

    try:
        args.run(args)
    except (DataError, ConfigError, CheckpointError, OptionsError, *_loaded(BAD_INPUT)) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)
    except BrokenPipeError:
        # the reader of our output left (`gns eval ... | head`): end quietly, as other tools do;
        # stdout goes to /dev/null so that Python's flush at exit does not complain again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(EXIT_FAILED)
    except OSError as e:  # an output that became unwritable, or a full disk, after the checks
        print(f"error: {e.strerror or e}: {e.filename}", file=sys.stderr)
        raise SystemExit(EXIT_FAILED)
    except Exception as e:  # after OSError: a re-raise here reaches no other clause
        if not isinstance(e, _loaded(FAILED)):
            raise
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(EXIT_FAILED)
    except KeyboardInterrupt as e:  # a training says the step it stopped at and saved
        print(f"error: interrupted{': ' + str(e) if str(e) else ''}", file=sys.stderr)
        raise SystemExit(130)
    finally:
        warnings.formatwarning = formatwarning


if __name__ == "__main__":
    main()
