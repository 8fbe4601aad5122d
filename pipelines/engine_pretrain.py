"""Pretraining data for the real-cube GNS: tosses simulated by the engine identified on the same
real tosses (baselines.engine_tosses), written as a dataset whose train split is synthetic and whose
valid split is the real one (so validation always scores real tosses). With real_copies = k the
train split also holds every real training toss k times: one training on both, the real ones
weighted by k.

    synthetic_stage(out, real_data, engine, params, count, seed, real_copies=0) -> Dataset

The dataset is built in a temporary folder and renamed into place, so a crash leaves no half
dataset; a rerun with the same inputs (recorded in metadata.json) skips it.
"""
from __future__ import annotations

import json
from pathlib import Path

from baselines import baseline_engine
from baselines.engine_tosses import engine_tosses
from baselines.toss import GRAVITY
from plumbing import atomic_folder
from datagen.shards import METADATA_FILE, Dataset, shard_name, write_metadata, write_shard
from pipelines.common import finished_dataset, say

SHARD_SCENES = 100


def synthetic_stage(out: Path, real_data: Path, engine: str, params: dict, count: int, seed: int,
                    real_copies: int = 0, jitter: dict | None = None) -> Dataset:
    """jitter: engine_tosses' perturbations where they are not its defaults (speed_jitter, height_jitter)."""
    real = Dataset(real_data)
    made_from = {"engine": engine, "params": params, "count": count, "seed": seed,
                 "real_fingerprint": real.fingerprint, "real_copies": real_copies, **({"jitter": jitter} if jitter else {})}
    ds = finished_dataset(out, "made_from", made_from, "synthetic")
    if ds is not None:
        return ds
    say(f"synthetic: {count} {engine} tosses from perturbed starts of {real.num_scenes('train')} real ones"
        + (f", and those real ones {real_copies} times" if real_copies else ""))
    scenes = engine_tosses(real.load("train"), engine, baseline_engine(engine)[0](**params), count, seed,
                           real.frame_rate, GRAVITY, **(jitter or {})) + real.load("train") * real_copies
    with atomic_folder(out) as tmp:
        splits = {"train": {"num_scenes": len(scenes), "shards": []}}
        for k in range(0, len(scenes), SHARD_SCENES):
            name = shard_name("train", k // SHARD_SCENES)
            write_shard(tmp / name, scenes[k:k + SHARD_SCENES], real.meshes, attrs={"split": "train", "source": engine})
            splits["train"]["shards"].append(name)
        if real.num_scenes("valid"):
            valid = real.load("valid")
            write_shard(tmp / shard_name("valid", 0), valid, real.meshes, attrs={"split": "valid", "source": "contactnets"})
            splits["valid"] = {"num_scenes": len(valid), "shards": [shard_name("valid", 0)]}
        meta = {k: v for k, v in json.loads((real.root / METADATA_FILE).read_text()).items()
                if k not in ("splits", "provenance", "checksums", "fingerprint")}
        meta.update(source=f"{engine} tosses from perturbed starts of real ones (baselines.engine_tosses); "
                           "valid split: the real valid tosses",
                    splits=splits, made_from=made_from)
        write_metadata(tmp, meta)
    return Dataset(out)
