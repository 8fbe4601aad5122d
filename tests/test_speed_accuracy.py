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
    assert (out / "pareto.png").stat().st_size > 0 and "| pybullet |" in (out / "table.md").read_text()
