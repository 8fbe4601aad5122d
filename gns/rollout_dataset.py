"""`gns rollout`: a trained model's rollouts of a split written as a dataset, in the format the
data came in (docs/data_format.md), so the same reader and `datagen inspect` read them. Its
output folder is checked before any work, and an --overwrite replaces only an earlier rollout.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from plumbing import check_output_folder, check_writable, DataError, overlapping
from datagen.shards import Dataset, Scene, shard_name, write_metadata, write_shard
from gns.checkpoint import checkpoint_of, load_simulator, parse_device
from gns.evaluate import (DivergedError, check_ranges, diverged_line, load_split, options_record, provenance_of,
                          scene_label, timed_rollout)
from gns.spec import ModelSpec, RolloutOptions


def rollout_run(run: str | Path, data: str | Path, out: str | Path, split: str = "test", limit: int | None = None,
                options: RolloutOptions | None = None, device: str = "cpu",
                overwrite: bool = False, at_data_rate: bool = False,
                between: str = "learned") -> tuple[int, int, float, float | None]:
    """Roll out the scenes of a split with the model of `run` (options: how) and write them to
    `out`; diverged rollouts are left out, named in a warning and in the metadata. With
    `at_data_rate` a model that steps k recorded frames is written at every recorded frame, read
    between its steps as `gns eval --at-data-rate` reads it (`between`). Returns (scenes rolled
    out, scenes written, seconds, seconds of a compiled model's warm-up or None)."""
    device = parse_device(device, "--device")
    check_output(out, overwrite, data)
    ckpt = checkpoint_of(run)
    sim, saved = load_simulator(ckpt, device, options)
    spec = ModelSpec.from_dict(saved["spec"])
    ds, scenes = load_split(data, split, limit, spec.frame_rate)
    check_ranges(spec, ds, scenes)
    pred, seconds, warmup = timed_rollout(sim, scenes, ds.meshes, ds.frame_rate)
    diverged = [scene_label(sc, i) for i, (p, sc) in enumerate(zip(pred, scenes)) if "diverged_at_frame" in p.attrs]
    if len(diverged) == len(pred):
        raise DivergedError(f"every rollout diverged ({len(pred)} scenes: positions became inf or NaN); "
                            f"nothing written to {out}")
    if diverged:
        print(diverged_line(diverged, len(pred), f"not written (listed in {out}/metadata.json)"), file=sys.stderr)
    given, read_by = 3, None
    if at_data_rate and ds.stride > 1:
        from gns.at_data_rate import read_split_at_data_rate
        kept = [i for i, p in enumerate(pred) if "diverged_at_frame" not in p.attrs]
        pairs, full, read_by = read_split_at_data_rate([pred[i] for i in kept], kept, saved, between, data, split,
                                                       limit, ds.stride)
        read = dict(zip(kept, (p for p, _ in pairs)))
        pred = [read.get(i, p) for i, p in enumerate(pred)]   # a diverged rollout stays as it was, to be listed
        ds, given = full, 2 * ds.stride + 1
    info = {"run": str(run), "checkpoint": str(ckpt), "step": int(saved["step"]), "read_between": read_by,
            "data": str(data), "split": split, "given_frames": given, "seconds": seconds,
            "warmup_seconds": warmup, "object_steps": sim.rollout_counts, **options_record(sim),
            **provenance_of(saved, ds)}
    write_rollouts(out, pred, ds, split, info, overwrite=overwrite)
    return len(pred), len(pred) - len(diverged), seconds, warmup


def check_output(out: str | Path, overwrite: bool, data: str | Path | None = None) -> Path:
    """Refuse, before any work is done: an output folder that is, holds or lies in the input
    dataset `data`; an existing non-empty folder without `overwrite`; with `overwrite`, a
    folder that is not an earlier `gns rollout` output (only files this tool wrote are replaced);
    a folder that cannot be written."""
    out = Path(out)
    if data is not None and overlapping(out, data):
        raise DataError(f"--out {out} and --data {data} overlap (the same folder or one inside the other); "
                        "write the rollouts to a folder of their own")
    if not overwrite and _unfinished_rollout(out):
        raise DataError(f"--out {out} holds an unfinished gns rollout (shards without metadata.json: it was stopped "
                        "before the end); use --overwrite to replace it")
    if check_output_folder(out, overwrite, "use --overwrite to replace it"):
        _rollout_files(out)
    return check_writable(out)


def _rollout_files(out: Path) -> list[Path]:
    """The files an earlier `gns rollout` wrote into `out` (its metadata.json and the shards it
    lists, or the shards of one stopped before its metadata.json); DataError if `out` holds
    anything else, so --overwrite deletes nothing else."""
    unfinished = _unfinished_rollout(out)
    if unfinished:
        return unfinished
    try:
        meta = json.loads((out / "metadata.json").read_text())
        listed = [out / name for split in meta["splits"].values() for name in split["shards"]]
        ours = meta.get("generator") == "gns rollout"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        ours, listed = False, []
    if not ours:
        raise DataError(f"--overwrite only replaces an earlier gns rollout output, and {out} is not one "
                        "(no metadata.json written by gns rollout); choose another --out")
    names = {p.name for p in listed} | {"metadata.json"}
    others = sorted(p.name for p in out.iterdir() if p.name not in names)
    if others:
        raise DataError(f"--overwrite refuses {out}: besides an earlier rollout it holds {', '.join(others[:4])}"
                        f"{' ...' if len(others) > 4 else ''}; choose another --out")
    return [p for p in listed if p.exists()] + [out / "metadata.json"]


def _unfinished_rollout(out: Path) -> list[Path]:
    """The files of a `gns rollout` stopped before writing metadata.json (its last file): every
    file in `out` is a shard gns rollout wrote (a shard name, `rollout` set in the file's
    attributes) or a temporary file of the atomic writer under one of the format's names; [] if
    `out` is anything else."""
    import h5py
    from datagen.shards import dataset_files
    if not out.is_dir() or (out / "metadata.json").exists():
        return []
    entries = list(out.iterdir())
    ours = {p.name for p in dataset_files(out)}
    if not entries or any(p.name not in ours for p in entries):
        return []
    for p in entries:
        if p.name.startswith("."):   # a temporary file: torn by construction, nothing to read
            continue
        try:
            with h5py.File(p, "r") as f:
                if not f.attrs.get("rollout"):
                    return []
        except OSError:
            return []
    return entries


def write_rollouts(out: str | Path, scenes: list[Scene], source: Dataset, split: str, info: dict,
                   overwrite: bool = False, per_shard: int = 64) -> None:
    """Rollouts as a dataset in the documented format (the same reader reads them). Diverged
    rollouts (no finite pose) are left out and listed in the metadata as rollout.diverged."""
    out = check_output(out, overwrite, source.root)
    kept = [sc for sc in scenes if "diverged_at_frame" not in sc.attrs]
    diverged = [scene_label(sc, i) for i, sc in enumerate(scenes) if "diverged_at_frame" in sc.attrs]
    if not kept:
        raise DivergedError(f"every rollout diverged ({len(scenes)} scenes: positions became inf or NaN); "
                            f"nothing written to {out}")
    if out.exists() and any(out.iterdir()):
        for p in _rollout_files(out):
            p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    meshes = source.meshes
    names = []
    for k in range(math.ceil(len(kept) / per_shard)):
        name = shard_name(split, k)
        write_shard(out / name, kept[k * per_shard:(k + 1) * per_shard], meshes, attrs={"split": split, "rollout": 1})
        names.append(name)
    meta = {key: v for key, v in source.meta.items() if key not in ("splits", "format_version", "complete")}
    meta.update(generator="gns rollout", rollout={**info, "diverged": diverged}, frame_rate=source.frame_rate,
                splits={split: {"num_scenes": len(kept), "shards": names}})
    write_metadata(out, meta)
