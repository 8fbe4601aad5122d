"""A coarser mesh for the network (features.mesh_vertices): the mesh, and a model trained on it."""
import numpy as np
import pytest
import torch
from gns_fixtures import write_toss_dataset

import gns
from datagen.shapes import get_shape
from gns.coarse_mesh import coarsen, farthest_order, farthest_points, network_meshes, support_gap, vertices_for_gap
from gns.config import ConfigError
from gns.graph import MeshLibrary, mesh_edges
from gns.rigid import shape_match_packed
from gns.train import CheckpointError, read_checkpoint, train
from test_gns_train import quiet, tiny


@pytest.mark.parametrize("shape", ["sphere", "cylinder", "beveled_cube"])
def test_the_coarse_mesh_is_a_closed_outward_hull_of_mesh_vertices(shape):
    mesh = get_shape(shape)
    v, f = coarsen(mesh.vertices, mesh.faces, 16)
    assert len(v) == 16
    # every coarse vertex is a vertex of the mesh, none twice
    match = np.abs(v[:, None] - np.asarray(mesh.vertices)[None]).sum(-1).min(1)
    assert match.max() == 0 and len(np.unique(v, axis=0)) == 16
    # closed: every undirected edge borders exactly two triangles; all 16 vertices are used
    und = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, count = np.unique(und, axis=0, return_counts=True)
    assert (count == 2).all() and set(f.ravel()) == set(range(16))
    # wound outward: the enclosed volume (divergence theorem) is positive and the hull's
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert volume > 0
    # a closed triangulated surface of V vertices has 3V - 6 edges (Euler)
    assert len(mesh_edges(f)) == 2 * (3 * 16 - 6)


def test_the_choice_depends_on_the_mesh_only_and_small_meshes_stay_whole():
    mesh = get_shape("sphere")
    first = farthest_points(mesh.vertices, 12)
    assert np.array_equal(first, farthest_points(np.array(mesh.vertices, copy=True), 12))
    cube = get_shape("cube")
    v, f = coarsen(cube.vertices, cube.faces, 8)
    assert np.array_equal(v, cube.vertices) and np.array_equal(f, cube.faces)
    assert network_meshes({"cube": (cube.vertices, cube.faces)}, 0)["cube"][0] is cube.vertices
    with pytest.raises(ValueError, match="mesh_vertices"):
        coarsen(mesh.vertices, mesh.faces, 3)


def test_shape_matching_recovers_the_pose_from_an_off_centre_subset():
    # the coarse vertices' mean is not the centre of mass; the pose must still come out exact
    mesh = get_shape("beveled_cube")
    lib = MeshLibrary({"b": (mesh.vertices, mesh.faces)}, 16)
    graph = lib.pack(lib.shape_ids(["b"]), torch.tensor([1.4]), torch.tensor([0.4]), torch.tensor([0.3]))
    assert graph.num_nodes == 16 and graph.rest.mean(0).norm() > 0.05
    angle = 0.7
    rot = torch.tensor([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]],
                       dtype=torch.float64)
    centre = torch.tensor([0.3, -2.0, 1.5], dtype=torch.float64)
    x = graph.rest @ rot.T + centre
    r, t, _ = shape_match_packed(x, graph.rest, graph.node_graph, 1)
    torch.testing.assert_close(r[0], rot)
    torch.testing.assert_close(t[0], centre)


def test_a_typo_in_mesh_vertices_is_one_line():
    with pytest.raises(ConfigError, match="features.mesh_vertices"):
        tiny("features.mesh_vertices=2")


# a few steps of the tiny model on a few single-cube tosses
SMALL = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")


def toss_out(model):
    return model.rollout(["cube"], [[0.0, 0.0, 2.0]], [[1.0, 0.0, 0.0, 0.0]], velocities=[[1.0, 0.0, 0.0]], steps=3)


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_trained_coarse_rolls_out_coarse_and_keeps_the_full_mesh(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "full", tiny(*SMALL), log=quiet)
    # fine-tuning may change the network's mesh (the weights do not depend on it) ...
    train(data, tmp_path / "coarse", tiny(*SMALL, "features.mesh_vertices=6",
                                          f"train.init_from={tmp_path / 'full'}"), log=quiet)
    ckpt = read_checkpoint(tmp_path / "coarse" / "latest.pt")
    assert ckpt["config"]["features"]["mesh_vertices"] == 6
    model = gns.load(tmp_path / "coarse")
    assert model.simulator.mesh_vertices == 6
    # ... the model keeps the full mesh, and builds its graphs from the coarse one
    assert len(model.meshes["cube"][0]) == 8
    out = toss_out(model)
    assert out.vertices.shape[1] == 6 and torch.isfinite(out.positions).all()
    # resuming is not fine-tuning: the graphs of a resumed run must be those it trained on
    with pytest.raises(CheckpointError, match="mesh_vertices"):
        train(data, tmp_path / "coarse", tiny("train.steps=8", "valid.every=0", "features.normalizer_steps=2"),
              resume=True, log=quiet)


def test_the_support_gap_of_a_cube_without_a_corner_is_that_corner_s_distance():
    cube = np.asarray(get_shape("cube").vertices, np.float64)
    side = np.ptp(cube, axis=0).max()
    assert support_gap(cube, np.arange(8)) == 0.0
    # without the corner c, the hull's support along c's diagonal falls to the three corners next
    # to it: side / sqrt(3) short, the most in any direction
    corner = int(np.argmax(cube.sum(1)))
    rest = np.array([i for i in range(8) if i != corner])
    assert support_gap(cube, rest) == pytest.approx(1 / np.sqrt(3), rel=1e-9)
    assert side == pytest.approx(1.0)


@pytest.mark.parametrize("gap", [0.03, 0.05, 0.08])
def test_a_round_mesh_gets_the_fewest_vertices_within_the_gap_and_a_box_no_more(gap):
    sphere, beveled = get_shape("sphere"), get_shape("beveled_cube")
    n = vertices_for_gap(sphere.vertices, 16, gap)
    order = farthest_order(sphere.vertices, len(sphere.vertices))
    assert 16 < n < len(sphere.vertices)
    assert support_gap(sphere.vertices, order[:n]) <= gap < support_gap(sphere.vertices, order[:n - 1])
    meshes = network_meshes({"sphere": (sphere.vertices, sphere.faces), "box": (beveled.vertices, beveled.faces)},
                            16, gap)
    assert len(meshes["sphere"][0]) == n
    # the beveled cube's 16-vertex hull is already within 2% of its size: it keeps 16
    assert support_gap(beveled.vertices, farthest_order(beveled.vertices, 16)) < 0.03
    assert len(meshes["box"][0]) == 16
    # a looser gap never asks for more vertices
    assert vertices_for_gap(sphere.vertices, 16, 2 * gap) <= n


def test_a_bad_mesh_support_gap_is_one_line():
    with pytest.raises(ConfigError, match="features.mesh_support_gap"):
        tiny("features.mesh_support_gap=-0.1", "features.mesh_vertices=6")
    with pytest.raises(ConfigError, match="needs features.mesh_vertices"):
        tiny("features.mesh_support_gap=0.05")


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_fine_tune_may_give_meshes_vertices_by_gap_and_the_model_keeps_them(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "six", tiny(*SMALL, "features.mesh_vertices=6"), log=quiet)
    # six of a cube's corners leave its hull far short of two of them: a gap of 1% asks for all 8
    train(data, tmp_path / "gap", tiny(*SMALL, "features.mesh_vertices=6", "features.mesh_support_gap=0.01",
                                       f"train.init_from={tmp_path / 'six'}"), log=quiet)
    assert read_checkpoint(tmp_path / "gap" / "latest.pt")["config"]["features"]["mesh_support_gap"] == 0.01
    model = gns.load(tmp_path / "gap")
    out = toss_out(model)
    assert out.vertices.shape[1] == 8 and torch.isfinite(out.positions).all()
    # two models reading different graphs cannot be averaged step by step
    with pytest.raises(ValueError, match="mesh_support_gap"):
        model.simulator.set_ensemble([gns.load(tmp_path / "six").simulator])
