"""Vertex-to-surface collision edges (gns.contacts, features.collision_mode = "surface")."""
import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes

from gns.config import ConfigError, build_config
from gns.contacts import closest_point_on_triangle, surface_edges
from gns.data import vertices_from_poses
from gns.contacts import collision_edges
from gns.graph import MeshLibrary

DTYPE = torch.float64


def test_closest_point_on_triangle_is_the_nearest_of_dense_samples():
    rng = np.random.default_rng(0)
    m = 300
    a, b, c, p = (torch.from_numpy(rng.normal(size=(m, 3))) for _ in range(4))
    got = closest_point_on_triangle(p, a, b, c)
    u = torch.from_numpy(rng.uniform(size=(m, 3000, 2)))
    u = torch.where((u.sum(-1, keepdim=True) > 1), 1 - u, u)
    samples = a[:, None] + u[..., :1] * (b - a)[:, None] + u[..., 1:] * (c - a)[:, None]
    brute = (samples - p[:, None]).norm(dim=-1).min(dim=1).values
    mine = (got - p).norm(dim=-1)
    assert (mine <= brute + 1e-9).all()          # never farther than any point of the triangle
    assert (brute - mine).max() < 0.1            # and the samples come close to it


def test_closest_point_regions():
    a, b, c = (torch.tensor([v], dtype=DTYPE) for v in ([0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]))
    cases = {(0.2, 0.2, 3.0): (0.2, 0.2, 0.0),   # above the face
             (-1.0, -1.0, 0.5): (0.0, 0.0, 0.0),  # beyond vertex a
             (0.5, -2.0, 0.0): (0.5, 0.0, 0.0),   # beyond edge ab
             (1.0, 1.0, 0.0): (0.5, 0.5, 0.0)}    # beyond edge bc
    for p, want in cases.items():
        got = closest_point_on_triangle(torch.tensor([p], dtype=DTYPE), a, b, c)
        assert torch.allclose(got, torch.tensor([want], dtype=DTYPE), atol=1e-12), (p, got)


def cubes(offset):
    """Two unit 8-vertex cubes in one scene, the second at `offset` (x, y, z) from the first."""
    lib = MeshLibrary(cube_meshes())
    graph = lib.pack(lib.shape_ids(["cube", "cube"]), torch.ones(2, dtype=DTYPE), torch.full((2,), 0.4),
                     torch.full((2,), 0.3), torch.zeros(2, dtype=torch.int64))
    pos = torch.tensor([[[0.0, 0.0, 0.0]], [offset]], dtype=DTYPE)
    rot = torch.eye(3, dtype=DTYPE).repeat(2, 1, 1)[:, None]
    return graph, vertices_from_poses(graph, pos, rot)[:, 0]


@pytest.mark.parametrize("gap", [0.05, 0.0, -0.05])
def test_face_contact_of_coarse_cubes_gets_edges_both_ways_with_the_true_gap(gap):
    # a cube on another's face, shifted by 0.5: no vertex pair is within the radius
    graph, x = cubes([1.0 + gap, 0.5, 0.1])
    assert len(collision_edges(x, graph, 0.15).senders) == 0
    e = surface_edges(x, graph, 0.15)
    objects = {(int(graph.node_graph[s]), int(graph.node_graph[r])) for s, r in zip(e.senders, e.receivers)}
    assert objects == {(0, 1), (1, 0)}
    assert torch.allclose(e.signed.min(), torch.tensor(gap, dtype=DTYPE), atol=1e-12)
    # the vector is the receiver minus its closest surface point, |vector| = |signed distance|
    assert torch.allclose(e.vectors.norm(dim=-1), e.signed[:, 0].abs(), atol=1e-12)


def test_objects_apart_get_no_surface_edges_and_translation_changes_nothing():
    graph, x = cubes([1.3, 0.0, 0.0])
    assert len(surface_edges(x, graph, 0.15).senders) == 0
    graph, x = cubes([1.02, 0.3, 0.1])
    e0 = surface_edges(x, graph, 0.15)
    e1 = surface_edges(x + torch.tensor([1e4, -1e4, 5.0], dtype=DTYPE), graph, 0.15)
    assert torch.equal(e0.senders, e1.senders) and torch.equal(e0.receivers, e1.receivers)
    assert torch.allclose(e0.vectors, e1.vectors, atol=1e-9) and torch.allclose(e0.signed, e1.signed, atol=1e-9)


def test_surface_edge_geometry_carries_the_gradient_of_the_positions():
    graph, x = cubes([1.05, 0.5, 0.1])
    plain = surface_edges(x, graph, 0.15)
    x = x.clone().requires_grad_()
    e = surface_edges(x, graph, 0.15)
    assert torch.equal(e.vectors, plain.vectors) and torch.equal(e.signed, plain.signed)
    e.signed.sum().backward()
    # the upper cube moving along +x opens the gaps, the lower one closes them
    upper = graph.node_graph == 1
    assert torch.isfinite(x.grad).all() and x.grad[upper, 0].sum() > 0 and x.grad[~upper, 0].sum() < 0


def test_collision_mode_is_checked():
    with pytest.raises(ConfigError, match="collision_mode"):
        build_config(overrides=["features.collision_mode=faces"])
    assert build_config(overrides=["features.collision_mode=surface"]).features.collision_mode == "surface"


@pytest.mark.parametrize("mode", ["surface", "face"])
def test_tiny_model_trains_and_rolls_out_with_collision_edges(tmp_path, mode):
    from datagen.cli import main as datagen_main
    from gns.evaluate import evaluate_run
    from gns.spec import RolloutOptions
    from gns.train import train
    data = tmp_path / "d"
    assert datagen_main(["toss", "--out", str(data), "--objects", "3-4", "--scenes", "4", "--test", "2",
                         "--frames", "10", "--shapes", "cube,cylinder", "--quiet"]) == 0
    cfg = build_config(path="configs/gns_tiny.toml",
                       overrides=["train.steps=10", "valid.every=0", f"features.collision_mode={mode}"])
    train(data, tmp_path / "run", cfg, log=lambda s: None)
    for options in (RolloutOptions(), RolloutOptions(symmetrize="d1", keep_apart=True)):
        results, pred, *_ = evaluate_run(tmp_path / "run", data, options=options, progress=False)
        assert all(np.isfinite(sc.positions).all() for sc in pred)
        assert results["num_object_pairs"] >= 2 and results["interpenetration_pct"] >= 0


def _deepest(x, graph):
    e = surface_edges(x, graph, 0.0)
    return float(-e.signed.min()) if len(e.senders) else 0.0


@pytest.mark.parametrize("offset", [[0.8, 0.3, 0.1], [0.2, 0.9, -0.3], [0.5, 0.5, 0.5]])
def test_separation_takes_overlapping_cubes_out_of_each_other(offset):
    from gns.contacts import separation
    graph, x = cubes(offset)
    assert _deepest(x, graph) > 0.05
    shift = separation(x, graph)
    moved = x + shift[graph.node_graph]
    assert _deepest(moved, graph) < 1e-6
    # equal cubes share the push: equal and opposite, so the pair's centre stays put
    assert torch.allclose(shift[0], -shift[1], atol=1e-12)
    # no more than the overlap along the push (one cube's width at most)
    assert float((shift[0] - shift[1]).norm()) <= 1.0 + 1e-9


def test_separation_leaves_objects_apart_and_lone_objects_alone():
    from gns.contacts import separation
    graph, x = cubes([1.01, 0.2, 0.0])
    assert torch.equal(separation(x, graph), torch.zeros(2, 3, dtype=DTYPE))
    lib = MeshLibrary(cube_meshes())
    one = lib.pack(lib.shape_ids(["cube"]), torch.ones(1, dtype=DTYPE), torch.full((1,), 0.4), torch.full((1,), 0.3))
    assert torch.equal(separation(x[:len(one.rest)], one), torch.zeros(1, 3, dtype=DTYPE))


def test_separation_does_not_push_an_object_into_the_floor():
    from gns.contacts import separation
    # the second cube rests on the floor (z = -0.5 under its centre) and the first sinks into it from above
    graph, x = cubes([0.0, 0.1, -0.8])
    shift = separation(x, graph, floor_z=-1.3)
    moved = x + shift[graph.node_graph]
    assert float(moved[graph.node_graph == 1, 2].min()) >= -1.3 - 1e-12
    # the cube on the floor stays, the one above takes the whole push, and they no longer overlap
    assert torch.allclose(shift[1], torch.zeros(3, dtype=DTYPE), atol=1e-12)
    assert _deepest(moved, graph) < 1e-6


def test_separation_gives_each_scene_of_a_batch_the_shifts_it_gets_alone():
    # scenes that settle after different numbers of iterations (a pair, a row of three that
    # pushes on, cubes apart): a scene done early leaves the iterations, which must not change
    # any scene's result, nor the other scenes of the batch change it
    from gns.contacts import separation
    lib = MeshLibrary(cube_meshes())
    layouts = [[[0.0, 0.0, 0.0], [0.8, 0.3, 0.1]],
               [[0.0, 0.0, 0.0], [0.75, 0.1, 0.0], [1.5, -0.1, 0.05], [2.2, 0.0, 0.0]],
               [[0.0, 0.0, 0.0], [1.2, 0.0, 0.0]]]

    def packed(chosen):
        offsets = [o for k in chosen for o in layouts[k]]
        scene = torch.tensor([i for i, k in enumerate(chosen) for _ in layouts[k]])
        n = len(offsets)
        graph = lib.pack(lib.shape_ids(["cube"] * n), torch.ones(n, dtype=DTYPE), torch.full((n,), 0.4),
                         torch.full((n,), 0.3), scene)
        pos = torch.tensor(offsets, dtype=DTYPE)[:, None] + torch.tensor([0.0, 0.0, 5.0], dtype=DTYPE)
        rot = torch.eye(3, dtype=DTYPE).repeat(n, 1, 1)[:, None]
        return graph, vertices_from_poses(graph, pos, rot)[:, 0]

    alone = [separation(*packed([k])[::-1], floor_z=0.0) for k in range(len(layouts))]
    graph, x = packed([0, 1, 2])
    together = separation(x, graph, floor_z=0.0)
    assert torch.equal(together, torch.cat(alone))
    assert together[:2].abs().sum() > 0 and together[2:6].abs().sum() > 0 and together[6:].abs().sum() == 0
    # Jacobi's 8 iterations leave a row of four a little inside each other, far less than before
    assert _deepest(x + together[graph.node_graph], graph) < _deepest(x, graph) / 20


def test_keep_apart_rollouts_keep_objects_out_of_each_other(tmp_path):
    # a tiny model of single objects (no collision edges: the projection is its only contact response)
    # lets crowded objects pass through each other; the projection does not
    from datagen.cli import main as datagen_main
    from gns.evaluate import evaluate_run
    from gns.spec import RolloutOptions
    from gns.train import train
    data = tmp_path / "d"
    assert datagen_main(["toss", "--out", str(data), "--objects", "5-6", "--scenes", "0", "--test", "3",
                         "--frames", "16", "--shapes", "cube,cylinder", "--quiet"]) == 0
    assert datagen_main(["toss", "--out", str(tmp_path / "single"), "--scenes", "4", "--frames", "16",
                         "--shapes", "cube,cylinder", "--quiet"]) == 0
    cfg = build_config(path="configs/gns_tiny.toml", overrides=["train.steps=5", "valid.every=0"])
    train(tmp_path / "single", tmp_path / "run", cfg, log=lambda s: None)
    plain, *_ = evaluate_run(tmp_path / "run", data, options=RolloutOptions(), progress=False)
    apart, pred, *_ = evaluate_run(tmp_path / "run", data, options=RolloutOptions(keep_apart=True), progress=False)
    assert all(np.isfinite(sc.positions).all() for sc in pred)
    assert plain["interpenetration_max_pct"] > 1.0
    assert apart["interpenetration_max_pct"] < 0.1 * plain["interpenetration_max_pct"]
    assert apart["pairs_passing_through_pct"] == 0
