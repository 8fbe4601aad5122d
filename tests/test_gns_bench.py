"""The training benchmark runs and prints one row per preset."""
import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_train.py"


def test_bench_train_prints_a_row_per_preset(capsys):
    spec = importlib.util.spec_from_file_location("bench_train", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.main(["--presets", "tiny,cpu", "--steps", "2", "--warmup", "1"])
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith(("tiny", "cpu"))]
    assert [r[0] for r in rows] == ["tiny", "cpu"]
    for r in rows:
        steps_per_sec, fraction = float(r[7]), float(r[12].rstrip("%"))
        assert steps_per_sec > 0 and 0 < fraction < 100
