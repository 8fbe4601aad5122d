"""The real-cube pipeline: its split (rotated copies kept together) and its tiny preset end to end."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from datagen.contactnets import read_toss
from pipelines import real_cubes
from pipelines.real_cubes_data import duplicate_groups, make_split, overlaps, read_tosses, same_toss, training_ids

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


def test_copies_are_found_in_files_and_against_an_external_folder(tmp_path, real):
    src = tmp_path / "src"
    shutil.copytree(SRC, src)
    torch.save(torch.from_numpy(np.pad(turned(real[229], 0.7), ((0, 0), (0, 6))))[None],
               src / "tosses_processed" / "456.pt")
    tosses = read_tosses(src)
    assert [g for g in duplicate_groups(tosses) if len(g) > 1] == [[229, 456]]
    ext = {9: turned(real[55], 2.5), 10: real[274][:-5]}
    assert overlaps(ext, tosses) == {9: [55]}


def test_tiny_preset_end_to_end_with_an_external_test_folder(tmp_path, capsys):
    out = tmp_path / "rc"
    args = ["--src", str(SRC), "--preset", "tiny", "--out", str(out), "--test-dir", str(SRC)]
    assert real_cubes.main(args) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["sizes"]) == {"1", "2"}
    for rows in results["sizes"].values():
        for key in ("position_error_pct", "rotation_error_deg", "penetration_pct"):
            for who in ("gns", "pybullet", "mujoco"):
                assert np.isfinite(rows[0][who][key])
        assert rows[0]["gns"]["num_scenes"] == rows[0]["pybullet"]["num_scenes"] == rows[0]["mujoco"]["num_scenes"] == 1
        for engine in ("pybullet", "mujoco"):
            fit = rows[0]["fits"][engine]
            assert fit["evaluations"] <= 3 and fit["objective"] <= fit["start_objective"]
    assert set(results["ablations"]) == {"full model", "no shape matching", "absolute encoding",
                                         "1 message-passing step", "no rotation augmentation"}
    assert set(results["noise"]["vertex"]) == {"0", "0.05"} and set(results["noise"]["track"]) == {"0", "0.5"}
    ext = results["external"]
    assert ext["sizes"]["2"][0]["gns"]["num_scenes"] == 3 and len(ext["overlap"]) == 3
    split = json.loads((out / "split.json").read_text())
    assert sorted(split["test"] + [i for g in split["pool"] for i in g]) == list(IDS)
    text = (out / "report.md").read_text()
    assert "| 2 | 0 |" in text and "PyBullet" in text and "MuJoCo" in text and "External test tosses" in text
    assert ext["sizes"]["2"][0]["mujoco"]["num_scenes"] == 3
    for name in ("fig4_position_error_pct", "fig4_rotation_error_deg", "fig4_penetration_pct", "fig5_ablations",
                 "fig7_vertex_noise", "fig7_track_noise"):
        assert (out / "plots" / f"{name}.png").stat().st_size > 0
    capsys.readouterr()
    assert real_cubes.main(args) == 0  # resumed: nothing is trained or fitted again
    err = capsys.readouterr().err
    assert "baseline: fitting" not in err and err.count("skipping") == 7
    assert sorted(p.name for p in (out / "baseline").glob("fit_*.json")) == [
        "fit_mujoco_n1_s0.json", "fit_mujoco_n2_s0.json", "fit_n1_s0.json", "fit_n2_s0.json"]
    assert json.loads((out / "results.json").read_text())["sizes"] == results["sizes"]


def test_bad_input_gives_one_error_line(tmp_path, capsys):
    assert real_cubes.main(["--src", str(tmp_path / "missing"), "--preset", "tiny", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0
    (tmp_path / "empty").mkdir()
    assert real_cubes.main(["--src", str(tmp_path / "empty"), "--preset", "tiny", "--out", str(tmp_path / "o")]) == 2
    assert "no N.pt toss files" in capsys.readouterr().err
    one = tmp_path / "one"
    one.mkdir()
    for i in (55, 229):
        shutil.copy(SRC / "tosses_processed" / f"{i}.pt", one)
    assert real_cubes.main(["--src", str(one), "--preset", "tiny", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: training size 2") and err.count("\n") == 1
    assert not (tmp_path / "o" / "runs").exists()


def test_baselines_alone_fit_both_engines_and_resume(tmp_path, capsys):
    from pipelines import real_cubes_baselines
    out = tmp_path / "bl"
    args = ["--src", str(SRC), "--out", str(out), "--sizes", "1", "2", "--budget", "2", "--test", "1", "--valid", "0"]
    assert real_cubes_baselines.main(args) == 0
    results = json.loads((out / "results.json").read_text())
    for n in ("1", "2"):
        for engine in ("pybullet", "mujoco"):
            r = results["sizes"][n][engine]
            assert r["num_scenes"] == 1 and np.isfinite(r["position_error_pct"])
            assert r["fit"]["evaluations"] == 2 and r["fit"]["train_tosses"] == int(n)
    assert "| MuJoCo | 2 |" in (out / "baselines.md").read_text()
    err = capsys.readouterr().err
    assert err.count("baseline: fitting") == 4
    assert real_cubes_baselines.main(args) == 0  # resumed: every fit is found
    assert "baseline: fitting" not in capsys.readouterr().err
    assert json.loads((out / "results.json").read_text())["sizes"] == results["sizes"]
    assert real_cubes_baselines.main(args[:-4] + ["--budget", "3", "--test", "1", "--valid", "0"]) == 0
    assert capsys.readouterr().err.count("baseline: fitting") == 4  # a new budget is a new fit


def test_baselines_alone_refuse_a_missing_mujoco_in_one_line(tmp_path, capsys, monkeypatch):
    from baselines import mujoco as baseline_mujoco
    from pipelines import real_cubes_baselines
    monkeypatch.setattr(baseline_mujoco, "available", lambda: False)
    args = ["--src", str(SRC), "--out", str(tmp_path / "bl"), "--sizes", "1", "--test", "1", "--valid", "0",
            "--engines", "mujoco"]
    assert real_cubes_baselines.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install -e '.[mujoco]'" in err
    assert real_cubes_baselines.available_engines() == ["pybullet"]  # the pipeline leaves it out, with a warning
    assert "leaving it out" in capsys.readouterr().err
