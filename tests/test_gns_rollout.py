"""Rollouts of a trained tiny model, their file format and `evaluate_run` (the MOVi-A pipeline:
test_movi_a_pipeline.py)."""
import json

import numpy as np
import pytest
import torch

from datagen.cli import main as datagen_main
from datagen.shards import Dataset, Scene
from gns.config import build_config
from gns.evaluate import evaluate_run
from gns.geometry import pose_to_vertices
from gns.spec import RolloutOptions
from gns.evaluate import rollout_scenes
from gns.rollout_dataset import write_rollouts
from gns.checkpoint import load_model
from gns.train import train


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("roll")
    data = root / "data"
    assert datagen_main(["toss", "--out", str(data), "--scenes", "8", "--test", "3", "--frames", "16",
                         "--shapes", "cube,sphere", "--quiet"]) == 0
    cfg = build_config(path="configs/gns_tiny.toml", overrides=["train.steps=30", "valid.every=0"])
    train(data, root / "run", cfg, log=lambda s: None)
    return data, root / "run"


def test_rollout_is_finite_rigid_and_starts_from_the_truth(trained):
    data, run = trained
    sim, _ = load_model(run / "latest.pt")
    ds = Dataset(data)
    true = ds.load("test")
    pred = rollout_scenes(sim, true, ds.meshes, ds.frame_rate, progress=False)
    for p, t in zip(pred, true):
        assert p.positions.shape == t.positions.shape and np.isfinite(p.positions).all()
        np.testing.assert_array_equal(p.positions[:3], t.positions[:3])
        np.testing.assert_allclose(np.linalg.norm(p.quaternions, axis=-1), 1.0, atol=1e-9)
        assert not np.allclose(p.positions[3:], t.positions[3:]), "a tiny model cannot be exact"
        rest = ds.meshes[p.shape[0]][0]
        verts = pose_to_vertices(p.positions[:, 0], p.quaternions[:, 0], p.scale[0], rest)
        d = np.linalg.norm(verts[:, :, None] - verts[:, None], axis=-1)
        np.testing.assert_allclose(d, d[:1].repeat(len(d), 0), atol=1e-9)  # pairwise distances kept


def test_object_steps_leave_out_the_padding_of_tracks_shorter_than_their_batch(trained):
    """A batch rolls every track out to its longest; the steps a shorter one is carried past its
    end are padding, not work the scene needed: the counts leave them out, the poses are cut."""
    from dataclasses import replace
    data, run = trained
    sim, _ = load_model(run / "latest.pt")
    ds = Dataset(data)
    cut = [replace(sc, **{k: getattr(sc, k)[:n] for k in ("positions", "quaternions", "velocities",
                                                          "angular_velocities")})
           for sc, n in zip(ds.load("test"), (16, 9, 5))]
    sizes, predict_next = [], sim.predict_next

    def spy(x_tm2, x_tm1, x_t, graph):
        sizes.append(len(x_t))
        return predict_next(x_tm2, x_tm1, x_t, graph)
    sim.predict_next = spy
    pred = rollout_scenes(sim, cut, ds.meshes, ds.frame_rate, progress=False)
    del sim.predict_next
    assert [p.num_frames for p in pred] == [16, 9, 5]
    # once the 9-frame track has ended too, the network sees the 16-frame track's vertices only (a
    # 5-frame cube's few vertices alone are not worth cutting the graph for: SUBGRAPH_MIN_SHARE)
    assert len(sizes) == 13 and sizes[6:] == [len(ds.meshes[cut[0].shape[0]][0])] * 7 < sizes[:6]
    assert sim.rollout_counts["object_steps"] == (16 - 3) + (9 - 3) + (5 - 3)
    assert sim.rollout_counts["network"] == sim.rollout_counts["object_steps"]   # no free flight, no sleep
    # the padding is not computed either: each track rolls out as it does alone, and an ended one stays put
    for sc, p in zip(cut, pred):
        [alone] = rollout_scenes(sim, [sc], ds.meshes, ds.frame_rate, progress=False)
        np.testing.assert_allclose(p.positions, alone.positions, rtol=0, atol=1e-6)


def test_rollouts_are_written_in_the_data_format(trained, tmp_path):
    data, run = trained
    sim, _ = load_model(run / "latest.pt", options=RolloutOptions(shape_matching=False))
    ds = Dataset(data)
    true = ds.load("test")
    pred = rollout_scenes(sim, true, ds.meshes, ds.frame_rate, progress=False)
    write_rollouts(tmp_path / "r", pred, ds, "test", {"run": str(run)})
    back = Dataset(tmp_path / "r")
    assert back.meta["rollout"]["run"] == str(run) and back.frame_rate == ds.frame_rate
    for a, b in zip(back.load("test"), pred):
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.quaternions, b.quaternions)


def test_evaluate_run_reports_metrics_and_plots(trained, tmp_path):
    data, run = trained
    results, pred, true, _ = evaluate_run(run, data, plots_dir=tmp_path / "plots", progress=False)
    for key in ("position_error_pct", "rotation_error_deg", "penetration_pct", "num_scenes"):
        assert key in results
    assert results["num_scenes"] == 3 and results["position_error_pct"] > 0
    assert (tmp_path / "plots" / "error_vs_time.png").stat().st_size > 0
    assert (tmp_path / "plots" / "rollout_worst.gif").stat().st_size > 0


def test_gns_eval_and_rollout_commands(trained, tmp_path, capsys):
    from gns.cli import main as gns_main
    data, run = trained
    gns_main(["eval", "--run", str(run), "--data", str(data), "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert "pos %" in out and "horizon 5" in out
    results = json.loads((tmp_path / "r.json").read_text())
    assert {"position_error_pct", "rotation_error_deg", "penetration_pct", "num_scenes"} <= set(results)
    gns_main(["rollout", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "roll")])
    assert Dataset(tmp_path / "roll").num_scenes("test") == 3
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        gns_main(["rollout", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "roll")])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists and is not empty" in err[0]


def test_missing_run_is_one_error_line(trained, tmp_path, capsys):
    from gns.cli import main as gns_main
    data, _ = trained
    with pytest.raises(SystemExit) as e:
        gns_main(["eval", "--run", str(tmp_path / "nope"), "--data", str(data)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: no checkpoint at")


def test_inputs_outside_training_are_named(trained, tmp_path, capsys):
    data, run = trained
    other = tmp_path / "other"
    assert datagen_main(["toss", "--out", str(other), "--scenes", "0", "--test", "2", "--frames", "16",
                         "--shapes", "cylinder", "--frame-rate", "16", "--set", "materials.metal.friction=0.0",
                         "--materials", "metal", "--quiet"]) == 0
    results, *_ = evaluate_run(run, other, progress=False)
    err = capsys.readouterr().err
    text = " | ".join(results["outside_training"])
    assert "frame rate 16" in text and "cylinder not seen" in text and "friction" in text
    assert err.count("warning: outside training:") == len(results["outside_training"])
    inside, *_ = evaluate_run(run, data, progress=False)
    assert inside["outside_training"] == []


def test_data_recorded_at_a_multiple_of_the_model_rate_are_read_at_its_rate(trained, tmp_path, capsys):
    """A 12 fps model on 24 fps data: every 2nd frame is used, and nothing is flagged."""
    data, run = trained
    fine = tmp_path / "fine"
    assert datagen_main(["toss", "--out", str(fine), "--scenes", "0", "--test", "2", "--frames", "31",
                         "--shapes", "cube,sphere", "--frame-rate", "24", "--quiet"]) == 0
    results, pred, true, ds = evaluate_run(run, fine, progress=False)
    assert ds.frame_rate == 12 and ds.stride == 2
    assert all(sc.num_frames == 16 for sc in true) and results["outside_training"] == []
    full = Dataset(fine).load("test")
    np.testing.assert_array_equal(true[0].positions, full[0].positions[::2])


@pytest.mark.parametrize("where", ["same", "inside", "parent"])
def test_rollout_refuses_an_output_that_overlaps_its_data_even_with_overwrite(trained, tmp_path, capsys, where):
    from gns.cli import main as gns_main
    data, run = trained
    out = {"same": data, "inside": data / "rollouts", "parent": data.parent}[where]
    shards = sorted(p.name for p in data.glob("*.h5"))
    with pytest.raises(SystemExit) as e:
        gns_main(["rollout", "--run", str(run), "--data", str(data), "--out", str(out), "--overwrite"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "overlap" in err[0]
    assert sorted(p.name for p in data.glob("*.h5")) == shards and Dataset(data).num_scenes("test") == 3


def _blow_up_graph_zero(monkeypatch):
    from gns.simulator import LearnedSimulator
    real = LearnedSimulator.predict_acceleration

    def boom(self, history, graph):
        a = real(self, history, graph)
        a[graph.node_graph == 0] = float("inf")          # the first object of every batch diverges
        return a
    monkeypatch.setattr(LearnedSimulator, "predict_acceleration", boom)


def test_a_diverged_rollout_is_named_and_left_out_not_a_crash(trained, tmp_path, capsys, monkeypatch):
    from gns.cli import main as gns_main
    from gns.evaluate import evaluate_run
    data, run = trained
    _blow_up_graph_zero(monkeypatch)
    results, pred, _, _ = evaluate_run(run, data, "test", progress=False)
    assert len(results["diverged_scenes"]) == 1 and results["num_scenes"] == 2
    assert np.isfinite(results["position_error_pct"])
    assert "1 of 3 rollouts diverged" in capsys.readouterr().err
    gns_main(["rollout", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "roll")])
    err = capsys.readouterr().err
    assert "1 of 3 rollouts diverged" in err and "not written" in err
    assert Dataset(tmp_path / "roll").num_scenes("test") == 2


@pytest.mark.parametrize("limit", ["0", "-2"])
def test_a_limit_below_one_is_one_line(trained, capsys, limit):
    from gns.cli import main as gns_main
    data, run = trained
    with pytest.raises(SystemExit) as e:
        gns_main(["eval", "--run", str(run), "--data", str(data), "--limit", limit])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--limit must be >= 1" in err[0]


def test_predicted_scenes_read_each_scenes_spin_off_its_own_poses():
    """Angular velocities come from one call over every track of a batch: a scene's spin is its
    own (a constant spin about its own axis, shorter scenes padded with NaN beside longer ones)."""
    from gns.evaluate import predicted_scenes
    from scipy.spatial.transform import Rotation
    dt, spins = 0.1, [np.array([0.0, 0.0, 3.0]), np.array([1.0, -2.0, 0.5]), np.array([0.0, 4.0, 0.0])]
    lengths, scenes = [12, 7, 9], []
    for length, w in zip(lengths, spins):
        q = Rotation.from_rotvec(np.arange(length)[:, None] * dt * w).as_quat()[:, [3, 0, 1, 2]]
        z = np.zeros((length, 1, 3))
        scenes.append(Scene(positions=z + 1.0, quaternions=q[:, None], velocities=z.copy(), angular_velocities=z + w,
                            shape=["cube"], material=["m"], scale=np.ones(1), mass=np.ones(1),
                            friction=np.ones(1), restitution=np.ones(1)))
    positions = np.full((max(lengths), 3, 3), np.nan)
    quaternions = np.full((max(lengths), 3, 4), np.nan)
    for j, sc in enumerate(scenes):
        positions[:sc.num_frames, j], quaternions[:sc.num_frames, j] = sc.positions[:, 0], sc.quaternions[:, 0]
    for sc, w, out in zip(scenes, spins, predicted_scenes(scenes, positions, quaternions, dt)):
        assert out.num_frames == sc.num_frames and "diverged_at_frame" not in out.attrs
        np.testing.assert_allclose(out.angular_velocities[:, 0], np.broadcast_to(w, (sc.num_frames, 3)), atol=1e-9)


def test_a_compiled_eval_warms_up_first_and_counts_only_the_timed_rollouts(trained, tmp_path, monkeypatch, capsys):
    """--compile rolls a first batch out before the clock starts (compiling takes tens of seconds):
    the warm-up is reported apart, and neither the scores nor the object-step counts see it.
    torch.compile is replaced by the identity here, so only the bookkeeping is under test."""
    from gns.cli import main as gns_main
    data, run = trained
    plain, *_ = evaluate_run(run, data, progress=False, free_flight=True, batch=2)
    assert plain["warmup_seconds"] is None
    monkeypatch.setattr(torch, "compile", lambda module, **kw: module)
    warmed, *_ = evaluate_run(run, data, progress=False, free_flight=True, batch=2, compile=True)
    assert warmed["warmup_seconds"] > 0
    assert warmed["object_steps"] == plain["object_steps"]   # 3 scenes, not 3 + the warm-up's 2
    assert warmed["position_error_pct"] == plain["position_error_pct"]
    gns_main(["eval", "--run", str(run), "--data", str(data), "--compile"])
    assert "compiling on a first batch, not counted" in capsys.readouterr().out
    gns_main(["rollout", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "r"), "--compile"])
    assert json.loads((tmp_path / "r" / "metadata.json").read_text())["rollout"]["warmup_seconds"] > 0
