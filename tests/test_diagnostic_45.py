"""pipelines.diagnostic_45: the sides table and the tiny pipeline end to end (its scenes: test_datagen_tilted.py)."""
import json

import numpy as np

from pipelines import diagnostic_45


def test_sides_table_and_mirrored_pairs():
    class S:
        def __init__(self, x):
            self.positions = np.array([[[0.0, 0, 0]], [[x, 0, 0]]])
            self.scale = np.array([1.4])
    true = [S(0.7), S(-0.7)]
    out = diagnostic_45.sides([S(0.7), S(0.7)], true, [44.0, 46.0])
    assert [r["agree"] for r in out["rows"]] == [True, False] and out["agree"] == 1
    assert out["pairs"] == [{"d": 1.0, "angles": [44.0, 46.0], "pybullet_mirrored": True, "gns_mirrored": False}]


def test_tiny_pipeline_end_to_end_and_rerun_skips(tmp_path, capsys):
    out = tmp_path / "d45"
    assert diagnostic_45.main(["--preset", "tiny", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert (out / "report.md").exists() and (out / "plots" / "fig3.png").stat().st_size > 1000
    assert results["angles"] == list(diagnostic_45.ANGLES)
    for name in ("plain", "symmetrized", "body frames"):
        assert [r["pybullet"] for r in results[name]["rows"]] == [1, 1, 1, 1, -1, -1, -1, -1]
        assert len(results[name]["pairs"]) == 4
    assert "| 44.75 |" in (out / "report.md").read_text()
    capsys.readouterr()
    assert diagnostic_45.main(["--preset", "tiny", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    for stage in ("drops", "data", "train", "eval"):
        assert f"{stage}: " in err and "skipping" in err.split(f"{stage}: ", 1)[1].splitlines()[0]


def test_missing_checkpoint_is_one_error_line(tmp_path, capsys):
    assert diagnostic_45.main(["--run", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and "nope.pt" in err[-1]
