"""The real-cube accuracy pipeline: tiny preset end to end, rerun skipping, exported models, bad input."""
import json

from test_real_cubes import SRC

from pipelines import real_cubes_accuracy
from gns.checkpoint import load_model


def test_tiny_preset_end_to_end_and_rerun(tmp_path, capsys):
    out, export = tmp_path / "acc", tmp_path / "models"
    args = ["--src", str(SRC), "--preset", "tiny", "--out", str(out), "--export", str(export)]
    assert real_cubes_accuracy.main(args + ["--workers", "2"]) == 0    # the two seeds in two processes
    results = json.loads((out / "results.json").read_text())
    row = results["sizes"]["2"]
    assert set(row) >= {"gns", "pybullet", "mujoco", "steps"} and results["seeds"] == [0, 1]
    for who in ("gns", "gns_engine_data", "pybullet", "mujoco"):
        assert row[who]["num_scenes"] == 1 and row[who]["position_error_pct"] >= 0
        seeds = [r["position_error_pct"] for r in row[who]["per_seed"]]
        assert len(seeds) == 2 and row[who]["position_error_pct"] == sum(seeds) / 2
        assert row[who]["spread"]["position_error_pct"] == [min(seeds), max(seeds)]
    assert set(row["pybullet"]["given_frames"].split("/")) <= {"3", "17"}
    # each seed its own tosses and its own engine fit
    fits = [json.loads((out / "baseline" / f"fit_mujoco_n2{t}.json").read_text()) for t in ("_s0", "_s1")]
    assert fits[0]["train_ids"] != fits[1]["train_ids"] and (out / "runs" / "gns_n2_s1" / "latest.pt").exists()
    assert (out / "plots" / "accuracy.png").stat().st_size > 1000
    assert "| 2 | GNS |" in (out / "report.md").read_text() and "lowest and highest seed" in (out / "report.md").read_text()
    # the GNS trained on the real tosses (x2) and 4 tosses of the MuJoCo tuned on them
    assert row["gns_engine_data"]["num_scenes"] == 1
    assert row["engine_data"] == {"synthetic": 4, "real_copies": 2, "jitter": real_cubes_accuracy.WIDER_STARTS}
    from datagen.shards import Dataset
    mixed = Dataset(out / "data" / "mujoco_n2_s0")
    assert mixed.num_scenes("train") == 4 + 2 * 2
    assert mixed.meta["made_from"]["jitter"] == real_cubes_accuracy.WIDER_STARTS     # the engine's starts widened
    assert "tuned-MuJoCo tosses" in (out / "report.md").read_text()
    sim, cfg = load_model(export / "real_cubes_n2.pt")   # the exported form loads alone
    assert cfg.features.frame_stride == 8 and cfg.train.all_phases and cfg.augment.body_symmetry
    assert cfg.train.rigid_loss == 1 and cfg.features.floor_clip == 1.5 and cfg.features.floor_signed
    assert cfg.model.message_passing_steps == 10
    load_model(export / "real_cubes_mujoco_n2.pt")
    # each GNS scored and exported with its reader between steps, fitted on its own training data
    from gns.checkpoint import read_checkpoint
    assert json.loads((out / "eval" / "gns_n2.json").read_text())["read_between"] == "learned"
    assert read_checkpoint(export / "real_cubes_mujoco_n2.pt")["between"]["data_fingerprint"] == mixed.fingerprint
    capsys.readouterr()
    before = (out / "eval" / "gns_n2.json").stat().st_mtime_ns
    assert real_cubes_accuracy.main(args) == 0                 # everything done: nothing retrained
    said = "".join(capsys.readouterr())
    assert "has reached step 30, skipping" in said and "fitting" not in said
    assert (out / "eval" / "gns_n2.json").stat().st_mtime_ns == before


def test_a_missing_source_is_one_line(tmp_path, capsys):
    assert real_cubes_accuracy.main(["--src", str(tmp_path / "nope"), "--preset", "tiny",
                                     "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
