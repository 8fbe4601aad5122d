"""The training benchmark runs and prints one row per preset."""
import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_train.py"


def learned_vs_physics(tmp_path, test: int, seed: int, shapes: str):
    """The bench_learned_vs_physics module and a dataset of `test` test scenes to run it on."""
    from datagen.cli import main as datagen_main
    data = tmp_path / "d"
    assert datagen_main(["toss", "--out", str(data), "--scenes", "0", "--test", str(test), "--seed", str(seed),
                         "--shapes", shapes, "--quiet"]) == 0
    spec = importlib.util.spec_from_file_location("bench_lvp", BENCH.parent / "bench_learned_vs_physics.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench, data


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


def test_bench_rollout_compares_variants_with_equal_results(capsys):
    spec = importlib.util.spec_from_file_location("bench_rollout", BENCH.parent / "bench_rollout.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.main(["--preset", "tiny", "--tracks", "3", "--frames", "6", "--repeats", "1"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("first edge layer", "batching"))]
    assert len(rows) == 4
    for row in rows:
        diff = float(row.split()[-1])
        assert diff < 1e-6  # a saving must not change the trajectories beyond rounding
    assert "network (encode, process, decode)" in out


def test_bench_collision_edges_matches_the_brute_force(capsys):
    spec = importlib.util.spec_from_file_location("bench_ce", BENCH.parent / "bench_collision_edges.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rows = bench.main(["--objects", "2,5", "--repeats", "1"])  # exits if any row differs from the brute force
    assert [r["edges"] for r in rows if r["layout"] == "apart"] == [0, 0]
    touching = [r["edges"] for r in rows if r["layout"] == "touching"]
    assert 0 < touching[0] < touching[1]  # more contacts, more edges


def test_bench_train_times_float32_against_bf16_autocast(capsys):
    spec = importlib.util.spec_from_file_location("bench_train", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.main(["--presets", "tiny", "--steps", "2", "--warmup", "1", "--autocast", "--rounds", "2"])
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.startswith("tiny")]
    assert [r[0] for r in rows] == ["tiny", "tiny+bf16", "tiny+bf16:"]
    ratio = float(rows[2][1].rstrip("x"))
    assert abs(ratio - float(rows[1][7]) / float(rows[0][7])) < 0.02   # the ratio of the rows printed


def test_bench_train_times_a_recipe_against_the_matmul_rate_of_its_own_shapes(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("bench_train_recipes", BENCH.parent / "bench_train_recipes.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.main(["--recipe", "tiny", "--steps", "2", "--warmup", "1", "--scenes", "3", "--cache", str(tmp_path)])
    out = capsys.readouterr().out
    [row] = [line.split() for line in out.splitlines() if line.startswith("tiny ")]
    assert row[1:4] == ["fp32", "1", "4"]     # the recipe's dtype, threads and batch size
    nodes, edges, steps_per_sec, gflop_per_step = float(row[4]), float(row[5]), float(row[7]), float(row[9])
    assert nodes > 0 and edges > 0 and steps_per_sec > 0 and gflop_per_step > 0
    of_shapes, of_peak = float(row[12].rstrip("%")), float(row[14].rstrip("%"))
    # both fractions are timings (a step against its products alone, against a 1024^3 product):
    # their order is the benchmark's finding, which a busy machine can upset, not a test's
    assert of_peak > 0 and of_shapes > 0
    assert row[-2:] == ["datagen", "3"] and "the first 3 of its 6 training scenes" in out
    assert "processor:" in out and "load average after" in out

    # the products a step runs, counted on a replay: forward, and backward without the input
    # layers' gradients with respect to the data
    run = bench.RecipeRun("tiny", None, None, 3, None, tmp_path, False)
    batch, _ = run.step()
    run.calls.clear()
    flops = sum(p.flops for p in run.products(batch))
    [(n, e, c, grad)] = run.calls
    forward = run.sim.network.forward_flops(n, e, c)
    assert grad
    assert 2.5 * forward < flops < 3 * forward

    # a later run of the recipe by name: its own settings (two pushforward steps: two calls a step)
    later = bench.RecipeRun("tiny:b_1", None, None, 3, None, tmp_path, False)
    assert later.cfg.train.unroll_steps == 2 and run.cfg.train.unroll_steps == 1
    later.step()
    assert len(later.calls) == 2
    with pytest.raises(SystemExit, match=r"no run 'c' \(a, b_1, b_2\)"):
        bench.RecipeRun("tiny:c", None, None, 3, None, tmp_path, False)


def test_bench_learned_vs_physics_times_pybullet_and_each_variant_on_the_same_scenes(tmp_path, capsys):
    import json

    bench, data = learned_vs_physics(tmp_path, 3, 5, "beveled_cube,cylinder,sphere")
    model = Path(__file__).parent / "data" / "gns_movi_a_small.pt"
    assert bench.main(["--run", str(model), "--data", str(data), "--repeats", "1", "--variants", "plain,free+bf16",
                       "--json", str(tmp_path / "b.json"), "--plot", str(tmp_path / "b.png")]) == 0
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["variant"] for r in rows] == ["PyBullet 240 Hz, 50 iterations", "GNS plain", "GNS free+bf16"]
    assert all(r["ms_per_simulated_second"] > 0 for r in rows)
    plain, fast = rows[1], rows[2]
    assert plain["network_share_pct"] == 100.0 and fast["network_share_pct"] < 100.0  # tosses start in the air
    assert abs(fast["position_error_pct"] - plain["position_error_pct"]) < 0.5 * plain["position_error_pct"]
    out = capsys.readouterr().out
    assert "| GNS free+bf16 |" in out and f"plot: {tmp_path / 'b.png'}" in out
    assert (tmp_path / "b.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_learned_vs_physics_compares_several_models_in_the_same_rounds(tmp_path):
    import json

    bench, data = learned_vs_physics(tmp_path, 2, 6, "cube")
    model = str(Path(__file__).parent / "data" / "gns_movi_a_small.pt")
    assert bench.main(["--run", model, "--run", model, "--data", str(data), "--repeats", "1",
                       "--variants", "plain,sym", "--json", str(tmp_path / "b.json")]) == 0
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["variant"] for r in rows[1:]] == [f"GNS {model} plain", f"GNS {model} sym"] * 2
    # the same model gives the same rollouts in both places; symmetrizing changes them
    assert rows[1]["position_error_pct"] == rows[3]["position_error_pct"]
    assert rows[2]["position_error_pct"] != rows[1]["position_error_pct"]


def test_bench_learned_vs_physics_times_an_ensemble_as_one_run(tmp_path):
    import json

    import pytest

    bench, data = learned_vs_physics(tmp_path, 2, 7, "cube")
    model = str(Path(__file__).parent / "data" / "gns_movi_a_small.pt")
    assert bench.main(["--run", model, "--run", f"{model}+{model}", "--data", str(data), "--repeats", "1",
                       "--variants", "free+bf16", "--json", str(tmp_path / "b.json")]) == 0
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["variant"] for r in rows[1:]] == [f"GNS {model} free+bf16", f"GNS {model}+{model} free+bf16"]
    # a model averaged with itself is the model
    assert abs(rows[1]["position_error_pct"] - rows[2]["position_error_pct"]) < 1e-3
    with pytest.raises(SystemExit, match=r"--run .*\+movi_a: ensemble member 1 differs"):
        bench.main(["--run", f"{model}+movi_a", "--data", str(data), "--repeats", "1",
                    "--variants", "plain"])


def test_bench_learned_vs_physics_front_and_replot(tmp_path):
    import json

    import pytest

    bench, _ = learned_vs_physics(tmp_path, 1, 8, "cube")
    # (throughput, error): the second is slower and worse than the first, so off the front
    xs, ys = [1.0, 0.5, 0.2, 0.1, 2.0], [20.0, 21.0, 15.0, 15.0, 30.0]
    assert bench.pareto_front(xs, ys) == [4, 0, 2]
    assert bench._short_names(["gns_movi_a_heading+gns_movi_a_spokes", "gns_movi_a_k3"]) == ["heading+spokes", "k3"]
    rows = [{"variant": "PyBullet", "x_pybullet": 1.0}] + [
        {"variant": f"GNS {m} {v}", "x_pybullet": x, "position_error_pct": y, "rotation_error_deg": y + 5}
        for (m, v), x, y in zip([("a", "free"), ("a", "free+sym"), ("b", "free"), ("b", "free+sym")],
                                [1.0, 0.3, 0.5, 0.1], [22.0, 20.0, 19.0, 18.0])]
    (tmp_path / "b.json").write_text(json.dumps({"run": ["a", "b"], "rows": rows}))
    assert bench.main(["--replot", str(tmp_path / "b.json"), "--plot", str(tmp_path / "b.png")]) == 0
    assert (tmp_path / "b.png").stat().st_size > 10_000
    with pytest.raises(SystemExit):
        bench.main(["--replot", str(tmp_path / "b.json")])
    with pytest.raises(SystemExit):
        bench.main(["--data", str(tmp_path)])


def test_bench_learned_vs_physics_reads_a_free_flight_clearance_and_refuses_a_bad_one():
    import pytest
    spec = importlib.util.spec_from_file_location("bench_lvp", BENCH.parent / "bench_learned_vs_physics.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    [(name, parts)] = bench.parse_variants("free+d1+bf16+freeze+clear0.5")
    assert [bench.clearance(p) for p in sorted(parts) if bench.clearance(p) is not None] == [0.5]
    for bad, message in (("free+clearx", "unknown variant part 'clearx'"), ("free+clear-1", "unknown variant part"),
                         ("bf16+clear0.5", "clearD sets free flight's height, it needs free")):
        with pytest.raises(SystemExit, match=message):
            bench.parse_variants(bad)


def test_compare_rollouts_pairs_the_scenes_and_a_setting_against_itself_differs_by_nothing(tmp_path, capsys):
    import json

    import pytest
    from datagen.cli import main as datagen_main
    spec = importlib.util.spec_from_file_location("compare", BENCH.parent / "compare_rollouts.py")
    compare = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compare)
    model = str(Path(__file__).parent / "data" / "gns_movi_a_small.pt")
    for seed, name in ((8, "d"), (9, "e")):
        assert datagen_main(["toss", "--out", str(tmp_path / name), "--scenes", "0", "--test", "3", "--valid", "2",
                             "--seed", str(seed), "--shapes", "cube,sphere", "--quiet"]) == 0
    sets = ["--data", str(tmp_path / "d"), "--data", f"{tmp_path / 'e'}:valid"]
    assert compare.main(["--a", f"{model}:d1", "--b", model, *sets, "--free-flight", "--resamples", "200",
                         "--json", str(tmp_path / "c.json")]) == 0
    rows = json.loads((tmp_path / "c.json").read_text())["rows"]
    assert [(r["split"], r["scenes"]) for r in rows] == [("test", 3), ("valid", 2), ("", 5)]
    for r in rows:
        pos = r["position_error_pct"]
        assert pos["low"] <= pos["A_minus_B"] <= pos["high"]
        assert pos["A_minus_B"] == pytest.approx(pos["A"] - pos["B"], abs=1e-9)   # paired: the means' difference
    assert rows[0]["position_error_pct"]["A_minus_B"] != 0.0    # symmetrizing changes the rollouts
    assert "| all (5) |" in capsys.readouterr().out
    assert compare.main(["--a", model, "--b", model, *sets[:2], "--json", str(tmp_path / "s.json")]) == 0
    same = json.loads((tmp_path / "s.json").read_text())["rows"][-1]["rotation_error_deg"]
    assert (same["A_minus_B"], same["low"], same["high"]) == (0.0, 0.0, 0.0)
    for bad, message in ((f"{model}:d3", "unknown symmetry group 'd3'"), (f"{model}+", "an empty run name")):
        with pytest.raises(SystemExit, match=message):
            compare.main(["--a", bad, "--b", model, *sets[:2]])


def test_speed_front_scores_pybullet_settings_and_a_model_against_the_data(tmp_path, capsys):
    import json

    bench, data = learned_vs_physics(tmp_path, 2, 9, "cube")
    spec = importlib.util.spec_from_file_location("speed_front", BENCH.parent / "speed_front.py")
    front = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(front)
    model = str(Path(__file__).parent / "data" / "gns_movi_a_small.pt")
    assert front.main(["--data", str(data), "--run", model, "--rates", "60,240", "--iterations", "10,50",
                       "--precisions", "f32", "--compile", "no", "--repeats", "1",
                       "--json", str(tmp_path / "f.json"), "--plot", str(tmp_path / "f.png")]) == 0
    saved = json.loads((tmp_path / "f.json").read_text())
    rows = saved["results"][0]["rows"]
    bullet = {(r["rate"], r["iterations"], r["client"]): r for r in rows if r["family"] == "pybullet"}
    assert len(bullet) == 8 and len(rows) == 9
    # the data's own settings remake the data exactly, whether the client is fresh or reused
    for client in ("fresh", "reused"):
        assert bullet[(240, 50, client)]["position_error_pct"] == 0.0
        assert bullet[(240, 50, client)]["rotation_error_deg"] == 0.0
        assert bullet[(60, 50, client)]["position_error_pct"] > 0.1
    learned = rows[-1]
    assert learned["family"] == "learned" and learned["position_error_pct"] > 0
    match = front.cheapest_as_good(learned, rows)
    assert match["position_error_pct"] <= learned["position_error_pct"]
    assert all(match["ms_per_simulated_second"] <= r["ms_per_simulated_second"] for r in bullet.values()
               if r["position_error_pct"] <= learned["position_error_pct"])
    out = capsys.readouterr().out
    assert "features:" in out and "load average" in out and "cheapest PyBullet as accurate" in out
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_collision_edges_on_a_dataset_counts_impacts_and_who_saw_them(tmp_path, capsys):
    from datagen.scenes import load_config
    from datagen.toss import generate
    cfg = load_config(None, ["scene.frames=12", "scene.shapes=['beveled_cube', 'sphere']", 'scene.objects="6"'])
    generate(cfg, 5, {"train": 0, "valid": 0, "test": 3}, tmp_path / "d", progress=False)
    spec = importlib.util.spec_from_file_location("bench_ce", BENCH.parent / "bench_collision_edges.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    *rows, impacts = bench.main(["--data", str(tmp_path / "d"), "--limit", "3"])
    assert sum(r["frames"] for r in rows) == 36
    assert impacts["impacts"] > 0       # six objects in a MOVi-A scene meet
    assert 0 <= impacts["seen_now"] <= impacts["impacts"] and 0 <= impacts["seen_ahead"] <= impacts["impacts"]
    assert "impacts (pairs closer than" in capsys.readouterr().out
