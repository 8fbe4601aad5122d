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
    assert diagnostic_45.main(["--preset", "tiny", "--out", str(out), "--shape", "cube"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert (out / "report.md").exists() and (out / "plots" / "fig3.png").stat().st_size > 1000
    assert (out / "plots" / "cases_d1.png").exists()
    assert results["angles"] == list(diagnostic_45.ANGLES)
    assert [(c["size"], c["start"]) for c in results["cases"]] == [
        (size, start) for size in ("small", "large") for start in ("edge", "drop 0.5", "drop 1")]
    for path in ("data", "api", "api held"):
        for variant in ("none", "d1"):
            tables = results["paths"][path][variant]
            assert len(tables) == 6
            for case, t in zip(results["cases"], tables):
                if path == "api held" and case["start"] == "edge":
                    assert t is None        # the edge is held in `api` already
                    continue
                # PyBullet: back below 45 degrees, over the edge above, from every start
                assert [r["pybullet"] for r in t["rows"]] == [1, 1, 1, 1, -1, -1, -1, -1]
                assert len(t["pairs"]) == 4
    assert results["totals"]["data"]["none"][1] == 48 and results["totals"]["api held"]["d1"][1] == 32
    report = (out / "report.md").read_text()
    assert "| cube | large (1.4) | drop 1 |" in report and "| **all** |" in report
    capsys.readouterr()
    assert diagnostic_45.main(["--preset", "tiny", "--out", str(out), "--shape", "cube"]) == 0
    err = capsys.readouterr().err
    for stage in ("drops", "data", "train", "eval"):
        assert f"{stage}: " in err and "skipping" in err.split(f"{stage}: ", 1)[1].splitlines()[0]


def test_an_unknown_variant_is_one_error_line(tmp_path, capsys):
    assert diagnostic_45.main(["--preset", "tiny", "--out", str(tmp_path / "o"), "--variants", "none,d3"]) == 2
    assert "d3" in capsys.readouterr().err.strip().splitlines()[-1]


def test_the_quick_preset_is_the_zoo_recipe():
    from pipelines.recipe import load_recipe
    recipe = load_recipe(diagnostic_45.PRESETS["quick"]["recipe"])
    assert recipe.zoo == ("diagnostic_45",) and recipe.data["kind"] == "tilted_drops"
    assert set(recipe.data["shapes"]) == {"cube", "beveled_cube"} and max(recipe.data["max_heights"]) == 1.0
    sets = dict(o.split("=", 1) for o in recipe.runs[0].overrides)
    assert sets["features.body_frame_free"] == "true" and sets["features.surface_edges"] == "false"
    assert "augment.body_symmetry" not in sets and sets["augment.mirror"] == "true"


def test_missing_checkpoint_is_one_error_line(tmp_path, capsys):
    assert diagnostic_45.main(["--run", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and "nope.pt" in err[-1]
