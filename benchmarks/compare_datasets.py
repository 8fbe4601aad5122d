"""One dataset's scenes scored as predictions of another's, scene by scene: how far two physics
set-ups started from the same states drift apart (the same seed gives the same starts whatever the
physics keys). Prints gns eval's table and writes its JSON if asked.

    datagen toss --objects 3-10 --shapes beveled_cube,cylinder,sphere --scenes 0 --test 100 --seed 11 --out data/ours
    datagen toss --config kubric_movi_a --scenes 0 --test 100 --seed 11 --out data/kubric
    python benchmarks/compare_datasets.py --truth data/ours --other data/kubric [--split test] [--json out.json]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from datagen.shards import Dataset  # noqa: E402
from gns.evaluate import score_predictions, write_json  # noqa: E402
from gns.metrics import format_table  # noqa: E402
from plumbing import DataError  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truth", required=True, help="dataset scored against")
    parser.add_argument("--other", required=True, help="dataset scored: the same scenes under other physics")
    parser.add_argument("--split", default="test")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()
    try:
        truth, other = Dataset(args.truth), Dataset(args.other)
        if truth.frame_rate != other.frame_rate:
            raise DataError(f"frame rates differ: {truth.frame_rate:g} and {other.frame_rate:g}")
        a, b = truth.load(args.split), other.load(args.split)
        if len(a) != len(b) or any(x.num_objects != y.num_objects or x.num_frames != y.num_frames
                                   or not np.allclose(x.positions[0], y.positions[0]) for x, y in zip(a, b)):
            raise DataError("the two datasets do not start from the same scenes (same seed, split and counts?)")
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    results = score_predictions(b, a, truth, seconds=0.0)
    results.update(truth=args.truth, other=args.other, split=args.split)
    print(format_table(results))
    if args.json:
        write_json(args.json, {k: v for k, v in results.items() if k != "per_scene"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
