"""pipelines/movi_a_sensitivity.py: exact physics re-run from a perturbed state. The unperturbed
re-run must reproduce the data exactly (else the study would not be running the data's physics),
a perturbation must move the trajectory from the frame after it, and a larger one must move it
more."""
import json

import pytest

from datagen.cli import main as datagen_main
from plumbing import DataError
from pipelines.movi_a_sensitivity import Perturbation, main, study


@pytest.fixture(scope="module")
def tosses(tmp_path_factory):
    out = tmp_path_factory.mktemp("sens") / "data"
    assert datagen_main(["toss", "--out", str(out), "--shapes", "beveled_cube,cylinder", "--scenes", "1",
                         "--valid", "0", "--test", "4", "--frames", "16", "--seed", "3", "--quiet"]) == 0
    return out


def test_the_unperturbed_rerun_reproduces_the_data_and_perturbations_grow_the_error(tosses):
    res = study(tosses, "test", perturbations=("exact:0", "turn:0", "restitution:0", "friction:0", "turn:0.1",
                                                "turn:3", "restitution:20"), progress=False)
    rows = {r["label"]: r for r in res["rows"]}
    # a perturbation of size 0 is none: setting a material to its own value must not change the
    # physics (PyBullet reports 0 restitution for these bodies: a study reading it back would
    # have set every restitution to 0)
    for label in ("exact (none)", "turn 0 deg", "restitution 0 %", "friction 0 %"):
        assert rows[label]["position_error_pct"] == 0.0 and rows[label]["rotation_error_deg"] == 0.0, label
    small, large = rows["turn 0.1 deg"], rows["turn 3 deg"]
    # the pose is turned after frame 2: the first predicted frame is off by about that angle
    assert small["horizons"]["1"]["rotation_error_deg"] == pytest.approx(0.1, rel=0.3)
    assert large["horizons"]["1"]["rotation_error_deg"] == pytest.approx(3.0, rel=0.3)
    assert large["rotation_error_deg"] > small["rotation_error_deg"] > 0
    assert rows["restitution 20 %"]["position_error_pct"] > 0
    assert res["num_scenes"] == 4 and res["data_fingerprint"]


def test_the_command_writes_results_and_report(tosses, tmp_path, capsys):
    assert main(["--data", str(tosses), "--limit", "2", "--perturb", "exact:0", "spin:1", "--out", str(tmp_path)]) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    assert [r["perturbation"] for r in saved["rows"]] == ["exact", "spin"] and saved["num_scenes"] == 2
    assert saved["rows"][1]["rotation_error_deg"] > 0
    assert "| spin 1 deg/frame |" in (tmp_path / "report.md").read_text()
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_trained_model_is_a_row_of_the_same_table(tosses, tmp_path):
    from gns.config import build_config
    from gns.train import train
    train(tosses, tmp_path / "run", build_config(path="gns_tiny", overrides=["train.steps=3", "valid.every=0"]),
          log=lambda _: None)
    assert main(["--data", str(tosses), "--limit", "2", "--perturb", "exact:0", "--run", str(tmp_path / "run"),
                 "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "results.json").read_text())["rows"]
    assert [r["perturbation"] for r in rows] == ["exact", "gns"]
    assert rows[1]["position_error_pct"] > 0 and "(its own rollout)" in rows[1]["label"]


def test_bad_perturbations_and_data_get_one_clear_error(tosses, tmp_path, capsys):
    with pytest.raises(DataError, match="unknown perturbation 'twist'"):
        Perturbation.parse("twist:1")
    with pytest.raises(DataError, match="size must be a finite number >= 0"):
        Perturbation.parse("turn:-1")
    assert main(["--data", str(tosses), "--perturb", "turn:abc", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'abc' is not a number" in err[0]
    assert main(["--data", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2
    assert "missing" in capsys.readouterr().err


def test_contact_errors_start_at_the_first_contact_and_parts_combine(tosses):
    res = study(tosses, "test", perturbations=("contact_turn:2", "contact_shift:2", "contact_turn:2+contact_shift:2"),
                progress=False)
    turn, shift, both = res["rows"]
    # the tosses start in the air: the first predicted frame is untouched, the rest is not
    for row in (turn, shift, both):
        assert row["horizons"]["1"]["rotation_error_deg"] == 0.0 and row["horizons"]["1"]["position_error_pct"] == 0.0
        assert row["rotation_error_deg"] > 0 and row["position_error_pct"] > 0
    assert both["perturbation"] == "contact_turn+contact_shift" and both["size"] is None
    assert both["label"] == "contact_turn 2 deg a contact step + contact_shift 2 % of size a contact step"
