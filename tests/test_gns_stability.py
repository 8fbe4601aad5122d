"""Stability at the extremes, on the shipped trained model and on constructed ones.

tests/data/gns_movi_a_small.pt is `gns export` of the model that
`python -m pipelines.movi_a --preset small` trained with the earlier small preset (cpu preset, 20k steps, 1000 MOVi-A-style
single-object tosses); a constructed model is a simulator whose decoder is set by hand, so its
exact trajectory is known and only the integrator, shape matching and features are on trial.
"""
import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from gns_fixtures import rolled_out

from datagen.cli import main as datagen_main
from datagen.shards import Dataset
from gns.config import build_config
from gns.data import ObjectTracks, feature_spec
from gns.graph import MeshLibrary
from gns.spec import outside_training
from gns.graph import EdgeSet
from gns.geometry import shape_match
from gns.simulator import LearnedSimulator
from gns.stepping import Sleep
from gns.spec import ModelSpec
from gns.stability import (REST_DRIFT_PCT, at_rest, extremes, long_rollouts, resting_scene)
from gns.checkpoint import load_model, read_checkpoint
from pipelines import stability as stability_pipeline

MODEL = Path(__file__).parent / "data" / "gns_movi_a_small.pt"


@pytest.fixture(scope="module")
def movi(tmp_path_factory):
    """Test tosses from the shipped model's training distribution."""
    out = tmp_path_factory.mktemp("stab") / "data"
    assert datagen_main(["toss", "--out", str(out), "--scenes", "0", "--test", "3", "--seed", "7",
                         "--shapes", "beveled_cube,cylinder,sphere", "--quiet"]) == 0
    ds = Dataset(out)
    return ds, ds.load("test")


@pytest.fixture(scope="module")
def trained():
    torch.set_num_threads(1)
    sim, _ = load_model(MODEL)
    return sim, ModelSpec.from_dict(read_checkpoint(MODEL)["spec"])


def constructed(ds, scenes, acceleration=(0.0, 0.0, 0.0)) -> LearnedSimulator:
    """A simulator that predicts the same acceleration (units per frame^2) for every vertex:
    decoder output zero, target normaliser mean set to `acceleration`."""
    cfg = build_config(path="configs/gns_tiny.toml")
    sim = LearnedSimulator(cfg.model, cfg.features, feature_spec(ds, scenes)).eval()
    with torch.no_grad():
        last = sim.network.decoder[-1]
        last.weight.zero_()
        last.bias.zero_()
        norm = sim.target_normalizer
        norm.count.fill_(1.0)
        norm.sum.copy_(torch.tensor(acceleration, dtype=torch.float64))
        norm.sum_squared.copy_(torch.tensor(acceleration, dtype=torch.float64) ** 2 + 1.0)
    return sim


def test_long_rollouts_of_the_trained_model_stay_finite_rigid_and_above_the_floor(movi, trained):
    ds, scenes = movi
    sim, _ = trained
    r = long_rollouts(sim, scenes, ds.meshes, floor_z=0.0, factor=10)
    assert r["steps"] == 10 * scenes[0].num_frames
    assert r["finite"] and r["rigid"] and r["above_floor"], r
    assert r["min_centre_height"] > 0


def test_constructed_model_at_rest_stays_at_rest_for_1000_steps(movi):
    ds, scenes = movi
    sim = constructed(ds, scenes)
    resting = [resting_scene(s, 1.4, ds.meshes, 0.0) for s in ("beveled_cube", "cylinder", "sphere")]
    rows = at_rest(sim, resting, ds.meshes, steps=1000)
    assert all(r["passed"] for r in rows), rows
    # far below the criterion: a float32 round trip anywhere in the loop would show as ~1e-5 %
    assert max(r["drift_pct"] for r in rows) < 1e-6


def test_constructed_gravity_model_falls_exactly_as_the_parabola(movi):
    """x_{t+1} = 2 x_t - x_{t-1} + g dt^2 is exact for constant acceleration: over 1000 steps with
    shape matching every frame, the centre must follow z0 - g t^2 / 2 to rounding."""
    ds, scenes = movi
    dt = 1.0 / ds.frame_rate
    g = 10.0
    sim = constructed(ds, scenes, acceleration=(0.0, 0.0, -g * dt * dt))
    sc = resting_scene("beveled_cube", 1.4, ds.meshes, floor_z=0.0)
    t = np.arange(sc.num_frames) * dt
    sc.positions[:, 0, 2] = 1e4 - 0.5 * g * t ** 2
    tracks = ObjectTracks([sc], MeshLibrary(ds.meshes))
    graph, verts, _ = tracks.track_vertices(torch.arange(1), 3)
    pred = sim.rollout(verts, graph, 1000)
    steps = np.arange(3, 1003) * dt
    centre = pred.mean(1)[:, 2].numpy() - verts[:, 0].mean(0)[2].item() + 1e4
    np.testing.assert_allclose(centre, 1e4 - 0.5 * g * steps ** 2, rtol=0, atol=1e-6)


@pytest.mark.xfail(strict=True, reason="measured: the small trained model slides off when at rest "
                                       "(drift 10-40x its size over 1000 steps); see docs/results.md")
def test_trained_model_at_rest_stays_at_rest(movi, trained):
    ds, _ = movi
    sim, spec = trained
    resting = [resting_scene(s, 1.4, ds.meshes, 0.0) for s in spec.shapes]
    rows = at_rest(sim, resting, ds.meshes, steps=1000)
    assert all(r["drift_pct"] < REST_DRIFT_PCT for r in rows), rows


def test_trained_model_at_rest_stays_at_rest_when_rollouts_sleep(movi, trained):
    ds, _ = movi
    sim, spec = trained
    resting = [resting_scene(s, 1.4, ds.meshes, 0.0) for s in spec.shapes]
    rows = at_rest(sim, resting, ds.meshes, steps=1000, sleep=True)
    assert all(r["drift_pct"] < REST_DRIFT_PCT for r in rows), rows


def test_sleeping_never_freezes_an_object_in_flight(movi):
    """Dropped from rest in mid-air (3 equal given frames): the object must fall exactly as
    without sleeping; only support by the floor lets a slow object sleep."""
    ds, scenes = movi
    dt = 1.0 / ds.frame_rate
    sim = constructed(ds, scenes, acceleration=(0.0, 0.0, -10.0 * dt * dt))
    sc = resting_scene("sphere", 1.4, ds.meshes, floor_z=0.0)
    sc.positions[..., 2] += 3.0
    graph, verts, _ = ObjectTracks([sc], MeshLibrary(ds.meshes)).track_vertices(torch.arange(1), 3)
    plain = sim.rollout(verts, graph, 10)
    sleeping = rolled_out(sim, verts, graph, 10, sleep=True)
    assert torch.equal(plain, sleeping)
    assert float(verts[:, -1, 2].mean() - sleeping[-1, :, 2].mean()) > 0.5 * 10.0 * (10 * dt) ** 2 * 0.9


def test_sleep_wakes_an_object_only_when_an_awake_object_touches_it():
    lib = MeshLibrary({"cube": (np.array([[-.5, -.5, -.5], [.5, -.5, -.5], [-.5, .5, -.5], [.5, .5, -.5],
                                          [-.5, -.5, .5], [.5, -.5, .5], [-.5, .5, .5], [.5, .5, .5]]),
                                np.array([[0, 1, 2]]))})
    graph = lib.pack(lib.shape_ids(["cube", "cube"]), torch.ones(2, dtype=torch.float64), torch.full((2,), .5),
                     torch.full((2,), .5))
    still = graph.rest + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) + \
        torch.tensor([[0.0, 0, 0]] * 8 + [[3.0, 0, 0]] * 8, dtype=torch.float64)
    moving = still.clone()
    moving[8:] += torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)  # object 1 slides: awake
    frames = [still, still, still]
    step = 10.0 / 144
    assert Sleep().asleep(frames, graph, step, 0.0, None).all()
    frames = [moving, still, still]
    alone = Sleep().asleep(frames, graph, step, 0.0, None)
    assert alone[:8].all() and not alone[8:].any()
    touching = EdgeSet(torch.tensor([8]), torch.tensor([0]))  # object 1's vertex near object 0's
    woken = Sleep().asleep(frames, graph, step, 0.0, touching)
    assert not woken.any()
    assert not Sleep().asleep([still, still, still], graph, step, None, None).any()  # no floor, no sleep


def test_extreme_inputs_are_handled_or_named_as_outside_training(movi, trained):
    ds, scenes = movi
    sim, spec = trained
    assert outside_training(spec, feature_spec(ds, scenes)) == []  # the base scenes are inside
    rows = {r["case"]: r for r in extremes(sim, spec, scenes, ds)}
    assert set(rows) == {"3x speed", "friction 0", "friction 1", "restitution 0", "restitution 1", "size 0.01x",
                         "size 100x", "10000 units from the origin", "float32 arrays"}
    assert all(r["passed"] for r in rows.values()), rows
    # an exact answer exists for these two: they are handled, not merely warned about
    for case in ("10000 units from the origin", "float32 arrays"):
        assert rows[case]["handled"] and rows[case]["warnings"] == [], rows[case]
    assert any("speed" in w for w in rows["3x speed"]["warnings"])
    assert any("scale" in w for w in rows["size 0.01x"]["warnings"])
    assert any("friction 0" in w for w in rows["friction 0"]["warnings"])
    assert any("restitution 1" in w for w in rows["restitution 1"]["warnings"])


def test_stability_pipeline_writes_a_report(movi, tmp_path, capsys):
    ds, _ = movi
    out = tmp_path / "report"
    assert stability_pipeline.main(["--run", str(MODEL), "--data", str(ds.root), "--out", str(out),
                                    "--limit", "1", "--factor", "2", "--rest-steps", "20"]) == 0
    text = (out / "report.md").read_text()
    assert "## Long rollouts" in text and "## At rest" in text and "3x speed" in text
    assert (out / "results.json").exists()


def test_stability_pipeline_missing_data_is_one_error_line(tmp_path, capsys):
    assert stability_pipeline.main(["--run", str(MODEL), "--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: not a dataset folder")


def _degenerate(points: np.ndarray, seed: int):
    rest = torch.from_numpy(points - points.mean(0))[None]
    q = np.random.default_rng(seed).normal(size=4)
    from gns.geometry import quat_to_matrix
    rot = torch.from_numpy(quat_to_matrix(q / np.linalg.norm(q)))[None]
    x = rest @ rot.transpose(1, 2) + torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    return rest, rot, x


def test_shape_match_of_a_flat_object_recovers_the_rotation():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.2, 0]], float)
    rest, rot, x = _degenerate(square, 1)
    r, _, proj = shape_match(x, rest)
    assert torch.allclose(r, rot, atol=1e-10) and torch.allclose(proj, x, atol=1e-10)


def test_shape_match_of_collinear_or_collapsed_points_is_a_finite_rotation():
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3.5, 0, 0]], float)
    rest, rot, x = _degenerate(line, 2)
    r, _, proj = shape_match(x, rest)
    # the spin about the line is undetermined; the points themselves must be matched
    assert torch.allclose(proj, x, atol=1e-10)
    assert torch.allclose(torch.linalg.det(r), torch.ones(1, dtype=torch.float64), atol=1e-10)
    collapsed = torch.zeros_like(x) + 5.0  # every predicted vertex at one point
    r, t, proj = shape_match(collapsed, rest)
    assert torch.isfinite(r).all() and torch.isfinite(proj).all()
    assert torch.allclose(torch.linalg.det(r), torch.ones(1, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(t, torch.full((1, 3), 5.0, dtype=torch.float64))


# Each zoo model with shapes it knows, in new scenes of 3-10 objects: its rollouts 10x the
# scenes' length stay finite in every scene, with the options it was scored with.
ZOO_SHAPES = {"movi_a": "beveled_cube,cylinder,sphere", "movi_a_fast": "beveled_cube,cylinder,sphere",
              "real_cubes": "cube", "real_cubes_16": "cube", "diagnostic_45": "cube"}


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    root = tmp_path_factory.mktemp("crowded")
    for shapes in set(ZOO_SHAPES.values()):
        assert datagen_main(["toss", "--shapes", shapes, "--objects", "3-10", "--scenes", "0", "--valid", "0",
                             "--test", "3", "--seed", "11", "--out", str(root / shapes), "--quiet"]) == 0
    return root


@pytest.mark.parametrize("name", sorted(ZOO_SHAPES))
def test_every_zoo_model_stays_finite_for_10x_the_length_of_scenes_of_3_to_10_objects(name, crowded):
    from gns.zoo import card
    ds = Dataset(crowded / ZOO_SHAPES[name])
    scenes = ds.load("test")
    assert min(sc.num_objects for sc in scenes) >= 3
    # diagnostic_45's card averages 96 network calls a step; the mirrors alone keep this test short
    options = dataclasses.replace(card(name).options, body_frames=False)
    sim, _ = load_model(card(name).file, options=options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # outside training (sizes, rates): finite all the same
        long = long_rollouts(sim, scenes, ds.meshes, 0.0, factor=10)
    assert long["steps"] == 10 * scenes[0].num_frames
    assert long["finite_scenes_pct"] == 100.0 and long["finite"]
