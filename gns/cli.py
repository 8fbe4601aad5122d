"""`gns` command line: one function per subcommand, registered on argparse subparsers.

A user error (bad data folder, unknown config key, unusable checkpoint, NaN loss) prints one
line `error: ...` on stderr and exits with status 2 (bad input) or 1 (training failed).
"""
from __future__ import annotations

import argparse
import sys

from datagen.shards import DataError
from gns.config import ConfigError

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


def cmd_train(args: argparse.Namespace) -> None:
    from gns.train import resolve_config, train

    overrides = list(args.set or [])
    if args.steps is not None:
        overrides.append(f"train.steps={args.steps}")
    cfg = resolve_config(args.out, args.resume, args.config, overrides)
    step = train(args.data, args.out, cfg, resume=args.resume, overwrite=args.overwrite)
    print(f"done at step {step}; checkpoints and metrics.jsonl in {args.out}")


def add_train_parser(sub) -> None:
    p = sub.add_parser("train", help="train a graph network simulator on a dataset folder",
                       description="Train a GNS on the train split of DIR; validate on its valid split.")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (metadata.json + shards)")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder for checkpoints and metrics.jsonl")
    p.add_argument("--config", metavar="TOML", help="preset, e.g. configs/gns_cpu.toml (default: built-in)")
    p.add_argument("--steps", type=int, metavar="N", help="train until step N (same as --set train.steps=N)")
    p.add_argument("--set", action="extend", nargs="+", metavar="KEY=VALUE",
                   help="override a config key, e.g. --set model.latent_size=64 train.batch_size=4")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue from RUN/latest.pt")
    mode.add_argument("--overwrite", action="store_true", help="delete RUN's checkpoints and start again")
    p.set_defaults(run=cmd_train)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gns", description="Graph network simulator for rigid bodies.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_train_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    # Imported after parsing so that `gns --help` and usage errors do not wait for torch.
    from gns.train import CheckpointError, TrainingError

    try:
        args.run(args)
    except (DataError, ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)
    except TrainingError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(EXIT_FAILED)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        raise SystemExit(130)


if __name__ == "__main__":
    main()
