"""The real-cube split: rotated copies found and kept on one side, nested training sets, copies in an external folder."""
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from datagen.contactnets import read_toss
from pipelines.real_cubes_data import (duplicate_groups, held_out_pool, make_split, overlaps, read_tosses, same_toss,
                                      training_ids)

SRC = Path(__file__).parent / "data" / "contactnets"
IDS = (55, 229, 274)


def turned(toss: np.ndarray, angle: float, shift=(3.0, -2.0)) -> np.ndarray:
    """The same toss turned about the vertical axis and moved on the table, as the data's copies are."""
    rz = Rotation.from_euler("z", angle)
    out = toss.copy()
    out[:, 0:3] = rz.apply(toss[:, 0:3]) + [*shift, 0.0]
    out[:, 3:7] = (rz * Rotation.from_quat(toss[:, [4, 5, 6, 3]])).as_quat()[:, [3, 0, 1, 2]]
    out[:, 7:10] = rz.apply(toss[:, 7:10])
    return out


@pytest.fixture(scope="module")
def real():
    return {i: read_toss(SRC / "tosses_processed" / f"{i}.pt") for i in IDS}


def test_rotated_copies_are_found_and_near_misses_are_not(real):
    tosses = dict(real)
    tosses[456] = turned(real[229], 1.1)
    tosses[500] = turned(real[55], -2.0)
    near = real[274].copy()
    near[40:, 2] += 1e-4  # the same length and start, but a different toss from frame 40 on
    tosses[600] = near
    assert same_toss(real[229], tosses[456]) and not same_toss(real[274], near)
    assert duplicate_groups(tosses) == [[55, 500], [229, 456], [274], [600]]


def test_split_keeps_copies_on_one_side_for_any_seed():
    groups = [[i] for i in range(40)] + [[100 + k, 200 + k] for k in range(10)]
    for seed in range(30):
        split = make_split(groups, n_test=9, n_valid=5, seed=seed)
        sides = {}
        for side in ("test", "valid"):
            for i in split[side]:
                sides[i] = side
        for g in split["pool"]:
            for i in g:
                sides[i] = "pool"
        assert len(sides) == 60
        for k in range(10):
            assert sides[100 + k] == sides[200 + k]
        assert 9 <= len(split["test"]) <= 10 and 5 <= len(split["valid"]) <= 6
        pool = sum(map(len, split["pool"]))
        assert sorted(training_ids(split, pool, 0)) == sorted(i for g in split["pool"] for i in g)
        small, large = training_ids(split, 8, 1), training_ids(split, 16, 1)
        assert large[:8] == small and len(set(large)) == 16  # nested subsets
    assert make_split(groups, 9, 5) == make_split(groups, 9, 5)  # fixed seed: the same split every time


def test_the_held_out_pool_shares_no_toss_or_copy_with_training():
    groups = [[i] for i in range(40)] + [[100 + k, 200 + k] for k in range(10)]
    split = make_split(groups, n_test=9, n_valid=5, seed=3)
    size = sum(map(len, split["pool"]))
    for n in (8, 17, 30):
        train, rest = set(training_ids(split, n, 0)), held_out_pool(split, n, 0)
        assert not train & set(rest) and not set(rest) & {*split["test"], *split["valid"]}
        # whole groups: a copy of a training toss is neither held out nor left in
        assert all(bool(train & set(g)) != bool(set(rest) & set(g)) for g in split["pool"])
        assert len(rest) <= size - n
    assert held_out_pool(split, size, 0) == []


def test_copies_are_found_in_files_and_against_an_external_folder(tmp_path, real):
    src = tmp_path / "src"
    shutil.copytree(SRC, src)
    torch.save(torch.from_numpy(np.pad(turned(real[229], 0.7), ((0, 0), (0, 6))))[None],
               src / "tosses_processed" / "456.pt")
    tosses = read_tosses(src)
    assert [g for g in duplicate_groups(tosses) if len(g) > 1] == [[229, 456]]
    ext = {9: turned(real[55], 2.5), 10: real[274][:-5]}
    assert overlaps(ext, tosses) == {9: [55]}
