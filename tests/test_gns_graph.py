"""Collision edges between objects of a scene: graph building, features, model, data, metric."""
from dataclasses import replace

import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes, write_toss_dataset

from datagen.cli import main as datagen_main
from datagen.shards import Dataset, Scene
from gns.config import FeatureConfig, ModelConfig, build_config
from gns.data import ObjectTracks, feature_spec, vertices_from_poses
from gns.geometry import quat_from_axis_angle
from gns.contacts import collision_edges, with_collision_edges
from gns.graph import MeshLibrary
from gns.metrics import evaluate_scenes, interpenetration_pct
from gns.evaluate import rollout_scenes
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec
from gns.checkpoint import load_model
from gns.train import train

R = 0.15
GAP = 0.02


def cubes(centres, scenes, angles=None):
    """Unit cubes (scale 1) at centres (G, 3) in the given scenes (G,): graph and vertices (N, 3)."""
    lib = MeshLibrary(cube_meshes())
    g = len(centres)
    graph = lib.pack(lib.shape_ids(["cube"] * g), torch.ones(g, dtype=torch.float64), torch.full((g,), 0.4),
                     torch.full((g,), 0.3), torch.tensor(scenes))
    rot = torch.eye(3, dtype=torch.float64).repeat(g, 1, 1)
    if angles is not None:
        from gns.data import rotation_z
        rot = rotation_z(torch.tensor(angles, dtype=torch.float64))
    x = vertices_from_poses(graph, torch.tensor(centres, dtype=torch.float64)[:, None], rot[:, None])[:, 0]
    return graph, x


def edge_set(e):
    return set(zip(e.senders.tolist(), e.receivers.tolist()))


def count(centres, scenes=(0, 0)):
    graph, x = cubes(centres, list(scenes))
    e = collision_edges(x, graph, R)
    return len(e.senders), graph, e


def test_one_object_scenes_and_far_objects_get_no_collision_edges():
    # touching cubes, but each alone in its scene
    assert count([[0, 0, 0], [0, 0, 1 + GAP], [0, 0, 2 + 2 * GAP]], scenes=(0, 1, 2))[0] == 0
    graph, x = cubes([[0, 0, 0], [0, 0, 1 + GAP]], [0, 0])
    graph.graph_scene = None           # no grouping: every graph alone
    assert len(collision_edges(x, graph, R).senders) == 0
    assert count([[0, 0, 0], [5, 0, 0]])[0] == 0
    assert count([[0, 0, 0], [0, 0, 1 + R + 0.01]])[0] == 0      # just beyond the radius


def test_touching_objects_get_edges_both_ways_between_different_objects():
    n, graph, e = count([[0, 0, 0], [0, 0, 1 + GAP]])
    assert n == 8                      # 4 top vertices of one face the 4 bottom ones of the other
    edges = edge_set(e)
    assert all((r, s) in edges for s, r in edges)
    assert (graph.node_graph[e.senders] != graph.node_graph[e.receivers]).all()
    assert (graph.node_scene[e.senders] == graph.node_scene[e.receivers]).all()


def test_edge_count_grows_with_contact():
    face = count([[0, 0, 0], [0, 0, 1 + GAP]])[0]
    edge = count([[0, 0, 0], [1 + GAP, 0, 1 + GAP]])[0]
    corner = count([[0, 0, 0], [1 + GAP, 1 + GAP, 1 + GAP]])[0]
    assert face > edge > corner > 0
    assert (face, edge, corner) == (8, 4, 2)


def test_collision_edges_equal_brute_force_on_random_scenes():
    rng = np.random.default_rng(3)
    centres = rng.uniform(0, 2.5, (9, 3))
    scenes = [0, 0, 0, 0, 1, 1, 1, 2, 3]
    graph, x = cubes(centres.tolist(), scenes, angles=rng.uniform(-np.pi, np.pi, 9).tolist())
    got = edge_set(collision_edges(x, graph, 0.4))
    d = torch.cdist(x, x)
    ns = graph.node_scene
    brute = (d < 0.4) & (ns[:, None] == ns[None, :]) & (graph.node_graph[:, None] != graph.node_graph[None, :])
    want = set(map(tuple, torch.nonzero(brute).tolist()))
    assert got == want and len(want) > 0


SPEC = ModelSpec(floor=None, materials_vary=False)


def simulator(collisions: bool):
    torch.manual_seed(0)
    return LearnedSimulator(ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, processor_repeats=1),
                            FeatureConfig(collision_radius=R), replace(SPEC, collision_edges=collisions))


def test_feature_selection_follows_the_dataset(tmp_path):
    single = Dataset(write_toss_dataset(tmp_path / "one", train=2, valid=0, frames=6))
    spec = feature_spec(single, single.load("train"))
    assert spec.collision_edges is False
    sim = LearnedSimulator(ModelConfig(latent_size=8, hidden_size=8), FeatureConfig(), spec)
    assert not [k for k in sim.state_dict() if "collision" in k]
    assert not sim.layout.collisions

    assert datagen_main(["toss", "--out", str(tmp_path / "multi"), "--objects", "2-3", "--scenes", "2",
                         "--frames", "6", "--quiet"]) == 0
    multi = Dataset(tmp_path / "multi")
    spec = feature_spec(multi, multi.load("train"))
    assert spec.collision_edges is True
    keys = [k for k in LearnedSimulator(ModelConfig(latent_size=8, hidden_size=8), FeatureConfig(), spec).state_dict()
            if "collision" in k]
    assert any(k.startswith("collision_normalizers.") for k in keys)
    assert any(k.startswith("network.collision_encoder.") for k in keys)
    assert any(k.startswith("network.blocks.0.collision.") for k in keys)


def test_translation_leaves_collision_edges_and_accelerations_unchanged():
    graph, x = cubes([[0, 0, 0.5], [0.3, 0.2, 1.55], [1.1, 0, 0.5], [4, 4, 4]], [0, 0, 0, 1], angles=[0, 0.4, 0.1, 0])
    history = torch.stack([x - 0.02, x - 0.01, x], dim=1)
    sim = simulator(True)
    sim.train()
    sim(history, graph)            # normaliser statistics
    sim.eval()
    shift = torch.tensor([1234.5, -678.9, 42.0], dtype=torch.float64)
    e0, e1 = collision_edges(x, graph, R), collision_edges(x + shift, graph, R)
    assert edge_set(e0) == edge_set(e1) and len(e0.senders) > 0
    a0 = sim.predict_acceleration(history, graph)
    a1 = sim.predict_acceleration(history + shift, graph)
    torch.testing.assert_close(a0, a1, atol=1e-5, rtol=1e-4)
    # the collision edges reach the output: without them the prediction differs
    a_none = sim.predict_acceleration(history, with_collision_edges(graph, x, 1e-9))
    assert not torch.allclose(a0, a_none)


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    root = tmp_path_factory.mktemp("multi")
    assert datagen_main(["toss", "--out", str(root / "data"), "--objects", "2-3", "--scenes", "6", "--valid", "1",
                         "--test", "2", "--frames", "12", "--quiet"]) == 0
    return root


def test_windows_hold_every_object_of_a_scene_rotated_together(multi):
    ds = Dataset(multi / "data")
    scenes = ds.load("train")
    tracks = ObjectTracks(scenes, MeshLibrary(ds.meshes))
    assert tracks.num_windows == sum(sc.num_frames - 3 for sc in scenes)
    windows = torch.tensor([0, 5, 5, tracks.num_windows - 1])
    plain = tracks.batch(windows)
    rotated = tracks.batch(windows, np.random.default_rng(0), rotate=True)
    objects = [scenes[int(s)].num_objects for s in tracks.window_scene[windows]]
    assert plain.graph.num_graphs == sum(objects)
    assert plain.graph.graph_scene.tolist() == [w for w, n in enumerate(objects) for _ in range(n)]
    # one angle per window: all distances between nodes of a window are kept
    for w in range(len(windows)):
        nodes = plain.graph.node_scene == w
        torch.testing.assert_close(torch.cdist(plain.history[nodes, -1], plain.history[nodes, -1]),
                                   torch.cdist(rotated.history[nodes, -1], rotated.history[nodes, -1]), atol=1e-6, rtol=0)


def test_tiny_model_trains_and_rolls_out_multi_object_scenes(multi):
    cfg = build_config(path="configs/gns_tiny.toml",
                       overrides=["train.steps=6", "valid.every=3", "valid.rollout_steps=3",
                                  "train.checkpoint_every=6", "features.collision_radius=0.2"])
    train(multi / "data", multi / "run", cfg, log=lambda s: None)
    sim, _ = load_model(multi / "run" / "latest.pt")
    assert sim.layout.collisions
    ds = Dataset(multi / "data")
    true = ds.load("test")
    pred = rollout_scenes(sim, true, ds.meshes, ds.frame_rate, progress=False)
    for p, t in zip(pred, true):
        assert p.positions.shape == t.positions.shape and np.isfinite(p.positions).all()
        np.testing.assert_array_equal(p.positions[:3], t.positions[:3])
    results = evaluate_scenes(pred, true, ds.meshes)
    assert np.isfinite(results["interpenetration_pct"]) and results["interpenetration_pct"] >= 0
    assert results["true_interpenetration_pct"] < 5
    assert results["num_object_pairs"] == sum(n * (n - 1) // 2 for n in (sc.num_objects for sc in true))


def two_cube_scene(offset, angle=0.0):
    T = 2
    pos = np.zeros((T, 2, 3))
    pos[:, 1] = offset
    quat = np.zeros((T, 2, 4))
    quat[..., 0] = 1
    quat[:, 1] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)
    z = np.zeros((T, 2, 3))
    return Scene(positions=pos, quaternions=quat, velocities=z, angular_velocities=z, shape=["cube", "cube"],
                 material=["metal", "metal"], scale=np.array([1.0, 2.0]), mass=np.ones(2),
                 friction=np.full(2, 0.4), restitution=np.full(2, 0.3))


def test_interpenetration_of_hand_made_poses():
    meshes = cube_meshes()
    # a cube of size 1 sunk 0.1 into a cube of size 2 (its bottom at 1 - 0.1): 10% of the smaller
    sunk = two_cube_scene([0, 0, 1.5 - 0.1])
    np.testing.assert_allclose(interpenetration_pct(sunk, meshes), 10.0, atol=1e-9)
    assert (interpenetration_pct(two_cube_scene([0, 0, 1.5 + 0.01], angle=0.3), meshes) == 0).all()
    assert (interpenetration_pct(two_cube_scene([5, 0, 0]), meshes) == 0).all()
    r = evaluate_scenes([sunk], [two_cube_scene([0, 0, 1.5])], meshes)
    assert r["interpenetration_pct"] == pytest.approx(10.0) and r["true_interpenetration_pct"] == 0
    one = Scene(**{k: (v[:, :1] if isinstance(v, np.ndarray) and v.ndim == 3 else v[:1])
                   for k, v in vars(sunk).items() if k != "attrs"})
    assert "interpenetration_pct" not in evaluate_scenes([one], [one], meshes)


def test_old_checkpoint_configs_without_collision_radius_stay_compatible():
    from gns.config import Config, architecture_differences, config_to_dict
    saved = config_to_dict(Config())
    del saved["features"]["collision_radius"]
    assert architecture_differences(saved, Config()) == []
    assert architecture_differences(saved, build_config(overrides=["features.collision_radius=0.3"]))


def test_flops_count_collision_edges():
    net = simulator(True).network
    assert net.forward_flops(100, 300, 50) > net.forward_flops(100, 300, 0) > simulator(False).network.forward_flops(100, 300)



@torch.no_grad()
@pytest.mark.parametrize("velocity", [False, True])
def test_each_object_is_seen_at_its_own_heading_and_the_scene_stays_exactly_equivariant(velocity):
    """features.canonical_heading turns each object to its own heading: an object far from the
    others predicts what it predicts alone, whichever way they move; collision vectors (with
    features.collision_velocity the relative velocity too) are turned into the receiver's heading,
    so a turn of the whole crowded scene about z turns the answer."""
    import math
    torch.manual_seed(0)
    sim = LearnedSimulator(ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, processor_repeats=1),
                           FeatureConfig(collision_radius=R, canonical_heading=True, collision_velocity=velocity),
                           replace(SPEC, collision_edges=True))
    graph, x = cubes([[0, 0, 0.5], [1.1, 0, 0.5], [6, 0, 0.5]], [0, 0, 0], angles=[0, 0.1, 0.3])
    moves = torch.tensor([[0.02, 0.01, 0.0], [-0.01, 0.03, 0.0], [0.0, -0.02, 0.01]], dtype=torch.float64)
    step = moves[graph.node_graph]
    history = torch.stack([x - 2 * step, x - step, x], dim=1)
    sim.train()
    sim(history, graph)
    sim.eval()
    a = sim.predict_acceleration(history, graph)
    far = graph.node_graph == 2
    others = (~far).to(torch.float64)[:, None, None]
    swung = history + others * torch.tensor([0.0, 0.05, 0.1], dtype=torch.float64)[None, :, None] * \
        torch.tensor([1.0, -1.0, 0.0], dtype=torch.float64)         # the others move another way
    assert not torch.allclose(sim.predict_acceleration(swung, graph)[~far], a[~far])
    torch.testing.assert_close(sim.predict_acceleration(swung, graph)[far], a[far], rtol=0, atol=1e-9)
    assert len(collision_edges(x, graph, R).senders) > 0
    for angle in (0.7, -2.4):
        c, s = math.cos(angle), math.sin(angle)
        q = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        turned = sim.predict_acceleration(history @ q.T, graph)
        assert float((turned - a @ q.T).abs().max() / a.abs().max()) < 1e-5, angle


def test_collision_velocity_is_the_relative_velocity_of_the_two_ends():
    """features.collision_velocity: v_r - v_s over the last frame, 3 more collision inputs; zero
    when the whole scene moves as one."""
    from gns.network import make_layout, raw_collision_features
    graph, x = cubes([[0, 0, 0.5], [1.1, 0, 0.5]], [0, 0])
    edges = collision_edges(x, graph, R)
    assert len(edges.senders) > 0
    moves = torch.tensor([[0.02, 0.01, 0.0], [-0.01, 0.03, 0.005]], dtype=torch.float64)[graph.node_graph]
    history = torch.stack([x - 2 * moves, x - moves, x], dim=1)
    got = raw_collision_features(history, edges, velocity=True)["collision_velocity"]
    want = (moves[edges.receivers] - moves[edges.senders]).to(torch.float32)
    torch.testing.assert_close(got, want)
    assert (want.abs().sum(1) > 0).all()
    together = torch.stack([x - 2 * moves[:1], x - moves[:1], x], dim=1)
    assert raw_collision_features(together, edges, velocity=True)["collision_velocity"].abs().max() < 1e-7
    assert "collision_velocity" not in raw_collision_features(history, edges)
    widths = [make_layout(FeatureConfig(collision_velocity=v), 0.0, True, collisions=True).collision_size
              for v in (False, True)]
    assert widths[1] == widths[0] + 3
