"""An output folder that several `datagen toss` runs meet at: the parts of a sharded generation,
which share it, and the one line for a run that finds it claimed by another.

With `--shard-index I --num-shards K` several runs (a Slurm array) write one folder: each writes
only its shards, and whichever run sees the last shard present finalises the metadata. The parts
share the folder's claim with each other (datagen/output.py) and take its plan lock to compare or
write the plan, so the plan is written once and no part adds its shards to another plan.
"""
from __future__ import annotations

import time
from pathlib import Path

from plumbing import DataError
from .output import (WRITTEN, ShardTask, check_output, plan_difference, plan_of, read_metadata, recorded_checksums,
                     remove_temporaries, same_plan, to_make)
from .shards import METADATA_FILE, write_metadata


def check_sharding(shard_index: int | None, num_shards: int | None, overwrite: bool) -> None:
    """Refuse a half-given or impossible part of a sharded generation, before anything is written."""
    if num_shards is None or shard_index is None:
        raise DataError("--shard-index and --num-shards go together")
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise DataError(f"--shard-index must be in 0..{num_shards - 1} and --num-shards >= 1, "
                        f"got {shard_index} of {num_shards}")
    if overwrite:
        raise DataError("--overwrite cannot be used with --num-shards: the runs would delete each other's "
                        "shards; clear the folder before starting them")


def prepare_shared_output(out: Path, meta: dict, mine: list[ShardTask]) -> list[ShardTask]:
    """The claimed folder of a part of a sharded generation (--num-shards), which other parts
    share: it may be new, empty, hold the same plan, or hold only the tool's files of a part
    that is just starting. Called under the plan lock, so the plan is written once, by the
    first part, and every other part compares its plan with it. Returns this part's shards to make."""
    check_output(out, meta, True, False, False)
    # Only this part's own leftovers: another part's temporary files may be shards being written.
    remove_temporaries(out, [t.name for t in mine], whole_run=False)
    if not (out / METADATA_FILE).exists():
        write_metadata(out, {**meta, WRITTEN: {}})
        return list(mine)
    old = same_plan(out, meta, "add shards to")
    recorded = recorded_checksums(old)
    todo = to_make(out, mine, recorded, "add shards to")
    if todo and old.get("complete") is True:
        # A finished dataset that lost a shard of this part: incomplete again until it is back.
        kept = {name: d for name, d in recorded.items() if (out / name).exists()}
        write_metadata(out, {**meta, WRITTEN: kept})
    return todo


def busy_error(out: Path, meta: dict, sharded: bool) -> DataError:
    """One line for a folder another run has claimed, naming how its plan differs when it has
    written one (it does so right after claiming: a moment's wait)."""
    planned, old = plan_of(meta), None
    deadline = time.monotonic() + 3.0
    # Read without the plan lock: metadata.json is only ever replaced whole, and taking the lock
    # here could leave its file behind in a folder whose holder has just cleaned up.
    while old is None and time.monotonic() < deadline:
        try:
            old = read_metadata(out, "read the plan") if (out / METADATA_FILE).exists() else None
        except DataError:
            break
        if old is None:
            time.sleep(0.05)
    who = "a whole `datagen toss` run" if sharded else "another `datagen toss`"
    key = plan_difference(old, planned) if old is not None else None
    if key:
        return DataError(f"cannot write {out}: {who} is writing a dataset there whose {key} differs from this command's")
    return DataError(f"cannot write {out}: {who} is writing it now; wait for it to end "
                     "(then --resume finishes the same plan)")
