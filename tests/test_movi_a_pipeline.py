"""pipelines/movi_a.py end to end: data, training, and one report setting the trained model beside
the zoo's MOVi-A model, PyBullet at coarser physics rates and the paper, on the same scenes."""
import json
import math

import pytest

from pipelines import movi_a


def run(out, preset="tiny"):
    return movi_a.main(["--preset", preset, "--out", str(out), "--workers", "1"])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("movi_a") / "tiny"
    assert run(out) == 0
    return out


def test_the_report_sets_the_model_beside_the_zoo_pybullet_and_the_paper(tiny):
    results = json.loads((tiny / "results.json").read_text())
    rows = {r["simulator"]: r for r in results["table"]}
    names = list(rows)
    assert names[0].startswith("this run's model (tiny preset, 40 steps)")
    assert names[1] == f"zoo `{movi_a.ZOO_MODEL}`"
    assert names[2:5] == ["PyBullet 60 Hz", "PyBullet 120 Hz", "PyBullet 240 Hz (the data's own rate)"]
    assert names[5].startswith("paper")
    for name, r in rows.items():
        scored = [r[k] for k in ("position_error_pct", "rotation_error_deg", "penetration_pct")]
        assert all(math.isfinite(v) and v >= 0 for v in scored), name
        if not name.startswith("paper"):
            assert r["ms_per_simulated_second"] > 0 and r["rollout_seconds"] > 0, name
    # the data's own rate re-simulated from the same initial states is the data, bit for bit
    exact = rows["PyBullet 240 Hz (the data's own rate)"]
    assert exact["position_error_pct"] == 0 and exact["rotation_error_deg"] == 0
    assert rows["PyBullet 60 Hz"]["position_error_pct"] > 0
    # the trained tiny model and the zoo's are different models, each rolled out as scored
    assert rows[names[0]]["position_error_pct"] != rows[names[1]]["position_error_pct"]
    assert results["zoo"]["rollout_options"]["symmetrize"] == "d1" and results["zoo"]["free_flight"]
    assert results["rollout_options"]["symmetrize"] == "none" and not results["free_flight"]
    assert results["paper"]["position_error_pct"] == 14.6 and results["num_scenes"] == 4
    assert results["seeds"] == {"data": 0, "train": 0} and results["scene_counts"]["test"] == 4
    assert results["machine"]["cores"] >= 1 and len(results["machine"]["load_at_report"]) == 3


def test_the_report_states_what_ran(tiny):
    text = (tiny / "report.md").read_text()
    results = json.loads((tiny / "results.json").read_text())
    for r in results["table"]:
        assert f"| {r['simulator']} | {r['position_error_pct']:.3g} |" in text
    assert "--symmetrize d1 --free-flight --free-clearance 0.5" in text
    assert "Machine: " in text and "load average" in text and "data seed 0" in text
    assert f"python -m pipelines.movi_a --preset tiny --out {tiny}" in text
    for plot in ("error_vs_time.png", "trajectory_median.png", "trajectory_worst.png"):
        assert (tiny / "plots" / plot).stat().st_size > 0


def test_a_rerun_skips_every_finished_stage(tiny, capsys):
    before = json.loads((tiny / "results.json").read_text())
    capsys.readouterr()
    assert run(tiny) == 0
    err = capsys.readouterr().err
    assert err.count("skipping") == 5, err   # data, training, the model's, the zoo's and PyBullet's scores
    assert "rolling out" not in err and "PyBullet at" not in err
    after = json.loads((tiny / "results.json").read_text())
    assert after["table"] == before["table"]


def test_training_further_scores_the_model_again_and_keeps_the_rest(tmp_path, capsys, monkeypatch):
    out = tmp_path / "t"
    assert run(out) == 0
    first = json.loads((out / "results.json").read_text())
    monkeypatch.setitem(movi_a.PRESETS, "tiny", {**movi_a.PRESETS["tiny"], "steps": 50})
    capsys.readouterr()
    assert run(out) == 0
    err = capsys.readouterr().err
    assert "resuming at step 40" in err and "rolling out the test split with the trained model" in err
    assert err.count("skipping") == 3   # the data, the zoo's and PyBullet's scores
    again = json.loads((out / "results.json").read_text())
    assert again["checkpoint_step"] == 50 and again["table"][0]["simulator"].endswith("50 steps)")
    assert again["table"][1:] == first["table"][1:]


def test_multi_object_preset_reports_interpenetration_and_leaves_the_zoo_out(tmp_path, capsys):
    out = tmp_path / "m"
    assert run(out, "multi_tiny") == 0
    results = json.loads((out / "results.json").read_text())
    assert results["num_object_pairs"] >= results["num_scenes"]  # 2-3 objects: at least one pair a scene
    assert results["interpenetration_pct"] >= 0 and results["true_interpenetration_pct"] >= 0
    assert results["zoo"] is None and not any(r["simulator"].startswith("zoo") for r in results["table"])
    assert "interpenetration between objects" in (out / "report.md").read_text().lower()
    assert "between objects" in capsys.readouterr().out  # the terminal table names it too


def test_the_presets_are_few_and_the_main_job_is_small():
    assert list(movi_a.PRESETS) == ["tiny", "small", "multi_tiny", "multi_small", "paper"]
    assert movi_a.PRESETS["small"]["counts"]["train"] == 1000 and movi_a.PRESETS["small"]["model"] == "cpu"
