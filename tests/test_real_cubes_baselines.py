"""pipelines.real_cubes_baselines run alone: both engines fitted, resumed, and a missing MuJoCo."""
import json
from pathlib import Path

import numpy as np

SRC = Path(__file__).parent / "data" / "contactnets"


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
