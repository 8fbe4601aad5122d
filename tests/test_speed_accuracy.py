import json

from pipelines import speed_accuracy


def test_tiny_sweep_writes_table_plot_and_a_point_per_setting(tmp_path):
    out = tmp_path / "sa"
    assert speed_accuracy.main(["--preset", "tiny", "--out", str(out)]) == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    p = speed_accuracy.PRESETS["tiny"]
    assert len([r for r in rows if r["family"] == "pybullet"]) == len(p["rates"]) * len(p["iterations"])
    assert len([r for r in rows if r["family"] == "gns speed"]) == len(p["architectures"]) * len(p["batches"])
    finer = {r["physics_rate"]: r["position_error_pct"] for r in rows if r["family"] == "pybullet"}
    assert finer[240] < finer[120], "a finer physics step must be closer to the fine reference"
    assert all(r["seconds_per_simulated_second"] > 0 for r in rows)
    # the trained sweep: one run per frame stride and per extra architecture, each scored
    trained = [r for r in rows if r["family"] == "gns batched"]
    t = p["train"]
    assert len(trained) == len(t["strides"]) + len(t["architectures"])
    rates = sorted(r["frame_rate"] for r in trained if r["knob"] == "frame stride")
    assert rates == sorted(12.0 * p["fine"] / s for s in t["strides"])
    assert all(r["steps"] == t["steps"] and r["position_error_pct"] >= 0 for r in trained)
    # each trained run again with free flight and bf16, scored and with its network share
    for family in ("gns fast", "gns fast sym"):
        fast = [r for r in rows if r["family"] == family]
        assert sorted(r["run"] for r in fast) == sorted(r["run"] for r in trained)
        assert all(0 <= r["network_share_pct"] <= 100 and r["position_error_pct"] >= 0 for r in fast)
    assert (out / "pareto.png").stat().st_size > 0 and "| pybullet |" in (out / "table.md").read_text()


def test_throughput_ratio_names_the_base_the_most_accurate_and_its_fast_rollout():
    bullet = {"family": "pybullet", "physics_rate": 240, "solver_iterations": 50, "seconds_per_simulated_second": 0.005}
    rows = [bullet,
            {"family": "gns batched", "knob": "frame stride", "run": "x/stride4", "frame_rate": 12.0,
             "seconds_per_simulated_second": 0.02, "position_error_pct": 50.0},
            {"family": "gns batched", "knob": "given", "run": "long", "frame_rate": 12.0,
             "seconds_per_simulated_second": 0.01, "position_error_pct": 30.0},
            {"family": "gns fast", "knob": "given", "run": "long", "frame_rate": 12.0, "fast": True,
             "precision": "bf16", "seconds_per_simulated_second": 0.004, "position_error_pct": 28.0},
            {"family": "gns fast sym", "knob": "given", "run": "long", "frame_rate": 12.0, "fast": True,
             "precision": "float32", "seconds_per_simulated_second": 0.01, "position_error_pct": 26.0}]
    lines = speed_accuracy.throughput_ratio(rows).splitlines()
    assert lines[1].startswith("stride4 at 12 fps: 0.25x")
    assert lines[2].startswith("long at 12 fps: 0.50x")
    assert lines[3].startswith("long at 12 fps, free flight + bf16 + compile: 1.25x") and "28% position" in lines[3]
    # each fast row names the precision its machine measured faster
    assert lines[4].startswith("long at 12 fps, free flight + float32 + compile + symmetrized: 0.50x")
    assert lines[5].startswith("at the best accuracy of any GNS rollout: long") and "26% position" in lines[5]


def test_dataset_stride_reads_every_kth_frame_and_refuses_bad_strides(tmp_path):
    import numpy as np
    import pytest
    from datagen.cli import main as datagen_main
    from datagen.shards import Dataset
    from plumbing import DataError
    out = tmp_path / "d"
    assert datagen_main(["toss", "--out", str(out), "--scenes", "0", "--test", "1", "--frames", "9",
                         "--frame-rate", "24", "--quiet"]) == 0
    full, third = Dataset(out).load("test")[0], Dataset(out, stride=3)
    assert third.frame_rate == 8.0
    sc = third.load("test")[0]
    assert sc.num_frames == 3 and sc.attrs["frame_stride"] == 3
    np.testing.assert_array_equal(sc.quaternions, full.quaternions[::3])
    for bad in (0, -1, 1.5):
        with pytest.raises(DataError, match="frame stride"):
            Dataset(out, stride=bad)
