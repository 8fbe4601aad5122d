"""The real-cube data: the ContactNets tosses read and checked, split once with a fixed seed into
test, valid and a training pool with rotated copies of a toss (the data hold 22 such pairs)
always on the same side, nested training subsets of the pool, and a dataset per split.

Used by pipelines/real_cubes.py, real_cubes_baselines.py, real_cubes_accuracy.py and
so all three score the same test tosses (and share one command line).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from datagen.contactnets import import_contactnets, list_toss_ids, read_toss
from datagen.shards import Dataset
from plumbing import DataError

SPLIT_SEED = 2022
DUPLICATE_TOL = 1e-6   # half-widths; the known rotated copies agree to 1e-15


def real_cubes_parser(module: str, doc: str, presets: dict | None = None, default: str | None = None,
                      out: str = "real_cubes") -> argparse.ArgumentParser:
    """The command line the real-cube pipelines share: --src, and with presets --preset and --out
    (default runs/<out>_<preset>)."""
    ap = argparse.ArgumentParser(prog=f"python -m pipelines.{module}", description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, required=True, help="ContactNets data folder (tosses_processed/N.pt)")
    if presets is not None:
        ap.add_argument("--preset", choices=sorted(presets), default=default)
        ap.add_argument("--out", type=Path, help=f"output folder (default runs/{out}_<preset>)")
    return ap


def read_tosses(src: Path) -> dict[int, np.ndarray]:
    """Every N.pt toss of a ContactNets folder, checked: {id: (T, 13)}."""
    ids = list_toss_ids(src)
    if not ids:
        raise DataError(f"no N.pt toss files in {src} (nor in {src}/tosses_processed)")
    root = src / "tosses_processed" if (src / "tosses_processed").is_dir() else src
    return {i: read_toss(root / f"{i}.pt") for i in ids}


def _profile(toss: np.ndarray) -> np.ndarray:
    """What a rotation about the vertical axis leaves unchanged: the height and the speed of the
    centre at every frame."""
    speed = np.linalg.norm(np.diff(toss[:, 0:3], axis=0), axis=1)
    return np.concatenate([toss[:, 2], speed])


def same_toss(a: np.ndarray, b: np.ndarray, tol: float = DUPLICATE_TOL) -> bool:
    """Whether two tosses are one toss, possibly turned about z and moved on the table: equal
    length, and heights and per-frame speeds equal within tol at every frame."""
    return a.shape == b.shape and bool(np.abs(_profile(a) - _profile(b)).max() <= tol)


def duplicate_groups(tosses: dict[int, np.ndarray], tol: float = DUPLICATE_TOL) -> list[list[int]]:
    """Tosses grouped with their copies (sorted groups, sorted by first id); singletons included."""
    parent = {i: i for i in tosses}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    by_length: dict[int, list[int]] = {}
    for i, t in tosses.items():
        by_length.setdefault(len(t), []).append(i)
    for ids in by_length.values():
        profiles = {i: _profile(tosses[i]) for i in ids}
        for x, i in enumerate(ids):
            for j in ids[x + 1:]:
                if np.abs(profiles[i] - profiles[j]).max() <= tol:
                    parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for i in tosses:
        groups.setdefault(root(i), []).append(i)
    return sorted(sorted(g) for g in groups.values())


def make_split(groups: list[list[int]], n_test: int, n_valid: int, seed: int = SPLIT_SEED) -> dict:
    """Shuffle the groups with `seed`; fill test, then valid, the rest is the training pool (in
    the shuffled order, which fixes the nested training subsets). A group is never cut, so test
    or valid can exceed its count by one."""
    order = np.random.default_rng(seed).permutation(len(groups))
    test, valid, pool = [], [], []
    for k in order:
        g = groups[k]
        if sum(map(len, test)) < n_test:
            test.append(g)
        elif sum(map(len, valid)) < n_valid:
            valid.append(g)
        else:
            pool.append(g)
    n = sum(map(len, groups))
    if not pool:
        raise DataError(f"only {n} tosses: not enough for {n_test} test + {n_valid} valid tosses and a training pool")
    flat = lambda gs: sorted(i for g in gs for i in g)  # noqa: E731
    return {"seed": seed, "test": flat(test), "valid": flat(valid), "pool": pool,
            "duplicates": [g for g in groups if len(g) > 1], "num_tosses": n}


def training_ids(split: dict, n: int, seed: int) -> list[int]:
    """The n training tosses of a seed: the first n of the pool, in the split's order for seed
    0 and in a reordering of its groups (seeded by seed) otherwise. Nested across sizes."""
    pool = split["pool"]
    size = sum(map(len, pool))
    if n > size:
        raise DataError(f"training size {n} needs {n} tosses but the training pool holds only {size} "
                        f"(after {len(split['test'])} test and {len(split['valid'])} valid tosses)")
    if seed:
        pool = [pool[k] for k in np.random.default_rng([SPLIT_SEED, seed]).permutation(len(pool))]
    return [i for g in pool for i in g][:n]


def held_out_pool(split: dict, n: int, seed: int) -> list[int]:
    """The training pool's tosses outside the n training tosses of a seed, as whole duplicate
    groups: a group of which one copy trains is left out entirely. More held-out tosses for
    choosing between models than the valid split alone (experiments/log.md)."""
    train = set(training_ids(split, n, seed))
    return sorted(i for g in split["pool"] if not train & set(g) for i in g)


def overlaps(external: dict[int, np.ndarray], source: dict[int, np.ndarray]) -> dict[int, list[int]]:
    """External tosses that are (possibly rotated) copies of source tosses: {external id: [ids]}."""
    by_length: dict[int, list[int]] = {}
    for i, t in source.items():
        by_length.setdefault(len(t), []).append(i)
    out = {}
    for e, t in external.items():
        hits = [i for i in by_length.get(len(t), []) if same_toss(t, source[i])]
        if hits:
            out[e] = hits
    return out


def import_stage(src: Path, out: Path, splits: dict[str, list[int]]) -> Path:
    """A dataset of these tosses per split, unless `out` already holds exactly that."""
    try:
        meta = Dataset(out).meta
        if {s: v.get("toss_ids") for s, v in meta["splits"].items()} == splits:
            return out
    except DataError:
        pass
    import_contactnets(src, out, splits=splits, overwrite=True, progress=False)
    return out
