"""features.floor_support: a coarse network mesh told where its full mesh is lowest."""
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from gns_fixtures import write_toss_dataset

import gns
from datagen.shapes import get_shape
from datagen.shards import Dataset
from gns.config import ConfigError, build_config
from gns.data import ObjectTracks, feature_spec
from gns.features import SUPPORT_SHARPNESS, floor_support, make_layout
from gns.graph import MeshLibrary
from gns.rigid import shape_match_packed
from gns.api import Model
from gns.train import _build_model, build_simulator, load_data, train
from test_gns_train import TINY, quiet, tiny

FLOOR = 0.0


def layout():
    cfg = build_config(path=TINY, overrides=["features.floor_support=true", "features.floor_clip=1.5",
                                             "features.floor_signed=true"])
    return make_layout(cfg.features, FLOOR, materials_vary=False)


def turn(axis, angle) -> torch.Tensor:
    return torch.from_numpy(trimesh.transformations.rotation_matrix(angle, axis)[:3, :3])


def support(graph, x):
    rot, centre, _ = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
    return floor_support(layout(), x, graph, rot, centre)


def asymmetric_mesh():
    """A convex mesh without any symmetry: a mirror image of it is another object."""
    points = np.random.default_rng(3).normal(size=(30, 3)) * [0.6, 0.4, 0.3]
    hull = trimesh.convex.convex_hull(points)
    return hull.vertices - hull.vertices.mean(0), hull.faces


def test_the_feature_is_the_full_mesh_low_point_which_the_coarse_mesh_misses():
    sphere = get_shape("sphere")
    lib = MeshLibrary({"sphere": (sphere.vertices, sphere.faces)}, 16, full_rest=True)
    graph = lib.pack(lib.shape_ids(["sphere"]), torch.tensor([1.4]), torch.tensor([0.4]), torch.tensor([0.3]))
    assert graph.num_nodes == 16 and graph.full_rest.shape == (1, len(sphere.vertices), 3)
    size = 1.4 * float(np.ptp(sphere.vertices, axis=0).max())
    centre = torch.tensor([0.5, -1.0, 0.9], dtype=torch.float64)
    misses = []
    for k, angle in enumerate(np.linspace(0.1, 3.0, 12)):
        rot = turn([1.0, 0.3 * k, 0.7], angle)
        x = graph.rest @ rot.T + centre
        full = graph.full_rest[0] @ rot.T + centre
        f = support(graph, x)
        low = float(full[:, 2].min())
        # the height is the full mesh's lowest vertex, the same for every node of the object
        assert torch.allclose(f[:, 3], torch.full((16,), low - FLOOR, dtype=torch.float64), atol=1e-9)
        point = f[:, :3] + x
        assert torch.allclose(point, point[:1].expand(16, 3), atol=1e-9)
        # a sphere is lowest under its centre; the low point sits within the weighting's band above
        assert float((point[0, :2] - centre[:2]).norm()) < 0.1 * size
        assert low <= float(point[0, 2]) < low + 3 * SUPPORT_SHARPNESS * size
        misses.append(float(x[:, 2].min()) - low)
    # the coarse hull's lowest vertex is often well above the full mesh's: what the feature adds
    assert max(misses) > 0.02 * size and min(misses) >= -1e-9


def test_a_face_lying_flat_reads_as_its_centre():
    cube = get_shape("cube")
    lib = MeshLibrary({"cube": (cube.vertices, cube.faces)}, full_rest=True)
    graph = lib.pack(lib.shape_ids(["cube"]), torch.tensor([1.0]), torch.tensor([0.4]), torch.tensor([0.3]))
    half = float(np.asarray(cube.vertices)[:, 2].max())
    centre = torch.tensor([2.0, 1.0, half + 0.2], dtype=torch.float64)
    x = graph.rest @ turn([0, 0, 1.0], 0.4).T + centre
    point = (support(graph, x)[:, :3] + x)[0]
    torch.testing.assert_close(point, torch.tensor([2.0, 1.0, 0.2], dtype=torch.float64))
    # far above the floor the height is clipped as the floor feature is
    assert float(support(graph, x + torch.tensor([0, 0, 9.0], dtype=torch.float64))[0, 3]) == 1.5


def tracks_of(tmp_path, vertices, faces, network_vertices=8):
    ds = Dataset(write_toss_dataset(tmp_path, train=3, valid=0, frames=10))
    lib = MeshLibrary({"cube": (vertices, faces)}, network_vertices, full_rest=True)
    return ds, ObjectTracks(ds.load("train"), lib)


def test_the_mirror_augmentation_mirrors_the_full_mesh_with_the_body_frame(tmp_path):
    _, tracks = tracks_of(tmp_path, *asymmetric_mesh())
    windows = torch.arange(tracks.num_windows)
    plain = tracks.batch(windows)
    mirrored = tracks.batch(windows, np.random.default_rng(0), mirror=True)
    flipped = (mirrored.history[:, -1, 0] - plain.history[:, -1, 0]).abs() > 1e-9
    assert 0 < int(flipped.sum()) < len(flipped)
    a, b = support(plain.graph, plain.history[:, -1]), support(mirrored.graph, mirrored.history[:, -1])
    # the mirror image of a toss is a toss of the mirrored object: the same heights, the offsets mirrored
    sign = torch.where(flipped, -1.0, 1.0).to(a)
    torch.testing.assert_close(b[:, 3], a[:, 3])
    torch.testing.assert_close(b[:, 0], a[:, 0] * sign)
    torch.testing.assert_close(b[:, 1:3], a[:, 1:3])


@torch.no_grad()
def test_symmetrized_predictions_stay_exactly_mirror_equivariant(tmp_path):
    ds, tracks = tracks_of(tmp_path, *asymmetric_mesh())
    cfg = build_config(path=TINY, overrides=["features.floor_support=true", "features.mesh_vertices=8"])
    sim = build_simulator(cfg, feature_spec(ds, ds.load("train"))).eval()
    b = tracks.batch(torch.tensor([0, 3, 6]))
    sim.symmetrize = True
    a = sim.predict_acceleration(b.history, b.graph)
    for m in ((-1.0, 1.0, 1.0), (1.0, -1.0, 1.0)):
        g = torch.tensor(m, dtype=torch.float64)
        graph = replace(b.graph, rest=b.graph.rest * g, full_rest=b.graph.full_rest * g)
        mapped = sim.predict_acceleration(b.history * g, graph)
        assert float((mapped - a * g).abs().max()) < 1e-6 * float(a.abs().max()), m
    # the feature matters to the answer: the object described without its full mesh's mirror differs
    g = torch.tensor((-1.0, 1.0, 1.0), dtype=torch.float64)
    wrong = sim.predict_acceleration(b.history * g, replace(b.graph, rest=b.graph.rest * g))
    assert float((wrong - a * g).abs().max()) > 1e-4 * float(a.abs().max())


def test_no_floor_is_one_clear_error():
    cfg = build_config(path=TINY, overrides=["features.floor_support=true"])
    with pytest.raises(ConfigError, match="features.floor_support needs a dataset with a floor"):
        make_layout(cfg.features, None, materials_vary=False)


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_fine_tuned_with_it_starts_as_it_was_and_rolls_out(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2", "features.mesh_vertices=6")
    train(data, tmp_path / "plain", tiny(*small), log=quiet)
    plain = gns.load(tmp_path / "plain")
    cfg = tiny(*small, "features.floor_support=true", f"train.init_from={tmp_path / 'plain'}")
    sim, _, spec, _, _ = _build_model(cfg, load_data(data, cfg)[0], None, np.random.default_rng(0))
    start = Model(sim.eval(), cfg, spec, plain.meshes, plain.device)
    assert [n for n, _ in start.simulator.layout.node_groups][-1] == "support"
    kwargs = dict(shapes=["cube"], positions=[[0.0, 0.0, 1.2]], quaternions=[[0.9, 0.3, 0.2, 0.1]],
                  velocities=[[1.0, 0.0, -4.0]], steps=6)
    torch.testing.assert_close(start.rollout(**kwargs).positions, plain.rollout(**kwargs).positions, rtol=0, atol=1e-9)
    train(data, tmp_path / "support", cfg, log=quiet)
    tuned = gns.load(tmp_path / "support")
    assert tuned.simulator.floor_support and torch.isfinite(tuned.rollout(**kwargs).positions).all()
