"""pipelines.real_cubes: the tiny preset end to end and bad input (its split: test_real_cubes_data.py)."""
import json
import shutil
from pathlib import Path

import numpy as np

from pipelines import real_cubes

SRC = Path(__file__).parent / "data" / "contactnets"
IDS = (55, 229, 274)


def test_tiny_preset_end_to_end_with_an_external_test_folder(tmp_path, capsys):
    out = tmp_path / "rc"
    args = ["--src", str(SRC), "--preset", "tiny", "--out", str(out), "--test-dir", str(SRC)]
    assert real_cubes.main(args + ["--workers", "2"]) == 0     # the GNS runs trained two at a time
    results = json.loads((out / "results.json").read_text())
    assert set(results["sizes"]) == {"1", "2"}
    assert {k for k in results["costs_seconds"] if k.startswith("train ")} == {f"train {r.name}" for r in (out / "runs").iterdir()}
    # the engines' fits ran in the pool beside the trainings: their costs reach the results too
    assert {k for k in results["costs_seconds"] if k.startswith("baseline fit ")} == \
        {f"baseline fit fit_{tag}n{n}_s0" for tag in ("", "mujoco_") for n in (1, 2)}
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
