"""pipelines.stiffness: the tiny preset end to end, a rerun that skips every stage, bad input."""
import json

import numpy as np
import pytest

pytest.importorskip("mujoco")  # the [mujoco] extra; the dev extra installs it

from pipelines import stiffness  # noqa: E402


def test_tiny_preset_end_to_end_then_a_rerun_skips_every_stage(tmp_path, capsys):
    out = tmp_path / "st"
    assert stiffness.main(["--preset", "tiny", "--out", str(out), "--workers", "2"]) == 0   # two sizes at a time
    results = json.loads((out / "results.json").read_text())
    assert set(results["levels"]) == {"soft", "hard"}
    for lv in results["levels"].values():
        assert set(lv["sizes"]) == {"2", "4"} and lv["penetration"]["num_tosses"] == 2
        for r in lv["sizes"].values():
            for model in ("gns", "gru"):
                assert all(np.isfinite(r[model][k]) for k in ("position_error_pct", "rotation_error_deg"))
    pen = {k: v["penetration"]["mean_pct"] for k, v in results["levels"].items()}
    assert pen["soft"] > pen["hard"]
    assert results["gru_config"]["steps"] == results["settings"]["steps"]           # the same budget
    assert {r["size"] for r in results["finding"]["soft_to_hard"]["gns position_error_pct"]} == {2, 4}
    report = (out / "report.md").read_text()
    assert "Soft to hard" in report and (out / "plots" / "error_vs_size.png").stat().st_size > 1000
    assert {f"train gns gns_{lv}_n{n}" for lv in ("soft", "hard") for n in (2, 4)} <= set(results["costs_seconds"])
    costs = [f.read_text() for f in sorted((out / "costs").iterdir())] + [(out / "costs.json").read_text()]
    capsys.readouterr()
    assert stiffness.main(["--preset", "tiny", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "train:" not in err and "data:" not in err
    assert [f.read_text() for f in sorted((out / "costs").iterdir())] + [(out / "costs.json").read_text()] == costs


def test_bad_input_is_one_error_line(tmp_path, capsys):
    assert stiffness.main(["--preset", "tiny", "--out", str(tmp_path / "o"), "--starts-from", str(tmp_path)]) == 2
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    assert stiffness.main(["--preset", "tiny", "--out", str(tmp_path / "mine"), "--fresh"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert len(err) == 2 and "no N.pt" in err[0] and "notes.txt" in err[1]
    assert (tmp_path / "mine" / "notes.txt").exists()


def test_a_run_folder_refuses_settings_that_change_what_it_learns_and_no_other(tmp_path):
    from pipelines.stiffness import _settings_guard
    from plumbing import DataError
    base = {"data": "d", "config": "gns_tiny", "set": ["train.lr_init=0.001", "train.steps=4"]}
    _settings_guard(tmp_path, base)
    # compiled, trained further, in another order: the same run
    _settings_guard(tmp_path, {**base, "set": ["train.compile=true", "train.steps=8", "train.lr_init=0.001"]})
    with pytest.raises(DataError, match="trained with other settings"):
        _settings_guard(tmp_path, {**base, "set": ["train.lr_init=0.01", "train.steps=8"]})
    with pytest.raises(DataError, match="trained with other settings"):
        _settings_guard(tmp_path, {**base, "data": "other"})
