"""Mesh edges, batch packing, vertices from poses, augmentation and noise."""
import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes, write_toss_dataset

from datagen.scenes import get_shape
from datagen.shards import Dataset
from plumbing import DataError
from gns.config import FeatureConfig
from gns.data import ObjectTracks, feature_spec, rotation_z, vertices_from_poses
from gns.network import make_layout
from gns.geometry import pose_to_vertices, quat_from_axis_angle, quat_to_matrix
from gns.graph import MeshLibrary, mesh_edges
from gns.geometry import acceleration_of, shape_match_packed


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return Dataset(write_toss_dataset(tmp_path_factory.mktemp("toss"), train=6, valid=2, frames=10))


@pytest.fixture(scope="module")
def tracks(dataset):
    return ObjectTracks(dataset.load("train"), MeshLibrary(dataset.meshes))


def test_mesh_edges_are_both_directions_without_duplicates():
    cube = get_shape("cube")
    edges = mesh_edges(cube.faces)
    # 12 triangles of a cube: 12 box edges + 6 face diagonals = 18 undirected, 36 directed.
    assert edges.shape == (36, 2)
    as_set = {tuple(e) for e in edges.tolist()}
    assert len(as_set) == 36
    assert all((r, s) in as_set for s, r in as_set)


def test_pack_offsets_nodes_and_edges_per_graph():
    meshes = {"cube": cube_meshes()["cube"], "tri": (np.eye(3), np.array([[0, 1, 2]]))}
    lib = MeshLibrary(meshes)
    ids = lib.shape_ids(["tri", "cube", "tri"])
    graph = lib.pack(ids, torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.1, 0.2, 0.3]), torch.tensor([0.4, 0.5, 0.6]))
    assert graph.num_nodes == 3 + 8 + 3 and graph.num_graphs == 3
    assert graph.node_graph.tolist() == [0] * 3 + [1] * 8 + [2] * 3
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    assert len(s) == 6 + 36 + 6
    # Every edge stays inside its graph and the last graph's edges are the first graph's, shifted.
    assert torch.equal(graph.node_graph[s], graph.node_graph[r])
    assert torch.equal(s[-6:], s[:6] + 11) and torch.equal(r[-6:], r[:6] + 11)
    assert torch.allclose(graph.rest[11:], 3 * torch.eye(3, dtype=torch.float64))
    assert torch.allclose(graph.rest[3:11], 2 * torch.from_numpy(cube_meshes()["cube"][0]))
    assert torch.allclose(graph.material[3], torch.tensor([0.2, 0.5]))


def test_vertices_from_poses_match_the_numpy_reference(tracks):
    graph, verts, centres = tracks.track_vertices(torch.tensor([0, 3]), 4)
    rest = cube_meshes()["cube"][0]
    for g, track in enumerate([0, 3]):
        start = int(tracks.start[track])
        pos = tracks.positions[start:start + 4].numpy()
        quat = tracks.quaternions[start:start + 4].numpy()
        expected = pose_to_vertices(pos, quat, float(tracks.scale[track]), rest)   # (4, V, 3)
        got = verts[graph.node_graph == g].transpose(0, 1).numpy()
        np.testing.assert_allclose(got, expected, atol=1e-12)
        np.testing.assert_allclose(centres[g].numpy(), pos)


def test_windows_cover_every_frame_quadruple(tracks):
    assert tracks.num_windows == 6 * (10 - 3)
    assert tracks.window_first.max() == 10 - 4


def test_rotation_augmentation_rotates_inputs_and_target_together(tracks):
    windows = torch.arange(12)
    plain = tracks.batch(windows)
    rotated = tracks.batch(windows, np.random.default_rng(1), rotate=True)
    graph = plain.graph
    frames_plain = torch.cat([plain.history, plain.target[:, None]], 1)       # (N, 4, 3)
    frames_rot = torch.cat([rotated.history, rotated.target[:, None]], 1)
    # One rigid transform per graph must map all four frames at once, and it must be a pure
    # rotation about the z axis through the origin.
    node_graph = graph.node_graph.repeat_interleave(4)
    rot, t, proj = shape_match_packed(frames_rot.reshape(-1, 3), frames_plain.reshape(-1, 3), node_graph,
                                      graph.num_graphs)
    assert torch.allclose(proj, frames_rot.reshape(-1, 3), atol=1e-9)
    assert torch.allclose(t, torch.zeros_like(t), atol=1e-9)
    assert torch.allclose(rot[:, 2, 2], torch.ones(graph.num_graphs, dtype=torch.float64), atol=1e-12)
    angles = torch.atan2(rot[:, 1, 0], rot[:, 0, 0])
    assert angles.std() > 0.5, "each graph gets its own angle"
    # Targets (accelerations) rotate with the inputs.
    acc_plain = acceleration_of(plain.history[:, 1], plain.history[:, 2], plain.target)
    acc_rot = acceleration_of(rotated.history[:, 1], rotated.history[:, 2], rotated.target)
    assert torch.allclose(acc_rot, (rot[graph.node_graph] @ acc_plain[..., None])[..., 0], atol=1e-12)


def test_rotation_z_is_a_rotation_about_up():
    r = rotation_z(torch.tensor([0.3, -2.0], dtype=torch.float64))
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    assert torch.allclose(r[:, :, 2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(2, 3))


def test_random_walk_noise_and_target_correction(tracks):
    windows = torch.arange(tracks.num_windows).repeat(20)
    clean = tracks.batch(windows)
    noisy = tracks.batch(windows, np.random.default_rng(0), noise_std=0.01)
    noise = noisy.history - clean.history                                     # (N, 3, 3)
    assert torch.equal(noise[:, 0], torch.zeros_like(noise[:, 0])), "the oldest frame is the walk's origin"
    # The last input frame carries noise of std noise_std; each velocity step std/sqrt(2).
    assert abs(float(noise[:, 2].std()) - 0.01) < 0.0005
    assert abs(float((noise[:, 1] - noise[:, 0]).std()) - 0.01 / np.sqrt(2)) < 0.0004
    # The target moves with the last frame's noise, so the target acceleration undoes exactly the
    # noise of the last input velocity.
    assert torch.allclose(noisy.target - clean.target, noise[:, 2])
    a_clean = acceleration_of(clean.history[:, 1], clean.history[:, 2], clean.target)
    a_noisy = acceleration_of(noisy.history[:, 1], noisy.history[:, 2], noisy.target)
    assert torch.allclose(a_noisy, a_clean - (noise[:, 2] - noise[:, 1]), atol=1e-12)


def test_material_and_floor_features_follow_the_dataset(tmp_path):
    varying = Dataset(write_toss_dataset(tmp_path / "mixed", train=2, valid=0, materials_vary=True))
    floorless = Dataset(write_toss_dataset(tmp_path / "nofloor", train=2, valid=0, floor=False))
    def groups(ds):
        spec = feature_spec(ds, ds.load("train"))
        return [n for n, _ in make_layout(FeatureConfig(), spec.floor_z, spec.materials_vary).node_groups]
    assert groups(varying) == ["velocity", "floor", "material", "rest_position"]
    assert groups(floorless) == ["velocity", "rest_position"]


def test_feature_spec_ranges(dataset):
    scenes = dataset.load("train")
    spec = feature_spec(dataset, scenes)
    assert spec.shapes == ("cube",) and spec.frame_rate == 12
    lo, hi = spec.ranges["scale"]
    assert lo >= 0.7 and hi <= 1.4
    fastest = max(np.linalg.norm(np.diff(s.positions, axis=0), axis=-1).max() for s in scenes) * 12
    assert spec.ranges["speed"][1] == pytest.approx(fastest)
    lo, hi = spec.ranges["angular_speed"]
    assert 0.5 - 1e-9 <= lo <= hi <= 3.0 + 1e-9, "the fixture spins at a constant rate in [0.5, 3] rad/s"


def test_non_finite_poses_are_a_data_error(dataset):
    scenes = dataset.load("train", limit=2)
    scenes[1].positions[3, 0, 2] = np.nan
    with pytest.raises(DataError, match="scene 1"):
        ObjectTracks(scenes, MeshLibrary(dataset.meshes), "train split")


def test_unknown_shape_is_a_data_error(dataset):
    scenes = dataset.load("train", limit=1)
    scenes[0].shape = ["teapot"]
    with pytest.raises(DataError, match="teapot"):
        ObjectTracks(scenes, MeshLibrary(dataset.meshes))


def test_quaternion_axis_convention(tracks):
    # A quarter turn about z maps the rest vertex (0.5, 0.5, 0.5) to (-0.5, 0.5, 0.5).
    lib = tracks.library
    graph = lib.pack(lib.shape_ids(["cube"]), torch.ones(1), torch.zeros(1), torch.zeros(1))
    rot = torch.from_numpy(quat_to_matrix(quat_from_axis_angle([0, 0, 1], np.pi / 2)))[None, None]
    verts = vertices_from_poses(graph, torch.zeros(1, 1, 3, dtype=torch.float64), rot)[:, 0]
    i = int(np.argmin(np.abs(graph.rest.numpy() - 0.5).sum(1)))
    assert torch.allclose(verts[i], torch.tensor([-0.5, 0.5, 0.5], dtype=torch.float64))
