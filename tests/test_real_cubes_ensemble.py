"""The real-cube ensemble pipeline: tiny preset end to end, the ensemble is the members' average,
rerun skipping, exported members, bad input."""
import json

from test_real_cubes import SRC

from pipelines import real_cubes_ensemble
from gns.checkpoint import load_model


def test_tiny_preset_end_to_end_and_rerun(tmp_path, capsys):
    out, export = tmp_path / "ens", tmp_path / "models"
    args = ["--src", str(SRC), "--preset", "tiny", "--out", str(out), "--export", str(export)]
    assert real_cubes_ensemble.main(args) == 0
    results = json.loads((out / "results.json").read_text())
    rows = results["rows"]
    assert set(rows) == {"real seed 0", "real seed 1", "mujoco seed 0", "mujoco seed 1", "ensemble of the real runs",
                         "ensemble of the mujoco runs", "ensemble of all runs"}
    for row in rows.values():
        assert row["test"]["num_scenes"] == 1 and "valid" not in row   # the 3 tosses in the repo: no valid split
    saved = json.loads((out / "eval" / "ensemble_of_all_runs.test.json").read_text())
    assert saved["ensemble"] == [str(out / "runs" / n) for n in ("mujoco_s1", "real_s0", "real_s1")]
    # an average of different models is none of them
    assert rows["ensemble of the real runs"]["test"] != rows["real seed 0"]["test"]
    assert results["mujoco"]["test"]["num_scenes"] == 1
    assert "| ensemble of all runs |" in (out / "report.md").read_text()
    sim, cfg = load_model(export / "gns_real_cubes_n2_e_mujoco1.pt")
    assert cfg.features.floor_signed and cfg.augment.body_symmetry and cfg.train.seed == 1
    capsys.readouterr()
    before = (out / "eval" / "ensemble_of_all_runs.test.json").stat().st_mtime_ns
    assert real_cubes_ensemble.main(args) == 0                  # everything done: nothing retrained
    said = "".join(capsys.readouterr())
    assert "has reached step 30, skipping" in said and "fitting" not in said
    assert (out / "eval" / "ensemble_of_all_runs.test.json").stat().st_mtime_ns == before


def test_a_missing_source_is_one_line(tmp_path, capsys):
    assert real_cubes_ensemble.main(["--src", str(tmp_path / "nope"), "--preset", "tiny",
                                     "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
