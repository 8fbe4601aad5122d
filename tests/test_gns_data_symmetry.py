"""Mirror and body-symmetry augmentation: the augmented windows are the same physics, relabelled
or mirrored, never a different motion."""
import numpy as np
import torch
import trimesh
from gns_fixtures import write_toss_dataset

from datagen.scenes import get_shape
from datagen.shards import Dataset
from gns.data import ObjectTracks
from gns.graph import MeshLibrary, mesh_symmetries
from gns.geometry import shape_match_packed


def _tracks(tmp_path):
    ds = Dataset(write_toss_dataset(tmp_path, train=4, valid=0, frames=10))
    return ObjectTracks(ds.load("train"), MeshLibrary(ds.meshes))


def test_symmetry_groups_of_the_shapes():
    assert len(mesh_symmetries(get_shape("cube").vertices)) == 24
    assert len(mesh_symmetries(get_shape("beveled_cube").vertices)) == 24
    cyl = mesh_symmetries(get_shape("cylinder").vertices)
    assert 1 < len(cyl) < 24
    assert np.allclose(cyl[0], np.eye(3))
    for s in cyl:  # a cylinder's symmetries keep its axis
        assert abs(abs(s[2, 2]) - 1) < 1e-12
    lopsided = trimesh.creation.box([1.0, 0.6, 0.3]).vertices + [0.01, 0.02, 0.03]
    assert len(mesh_symmetries(lopsided)) == 1


def test_body_symmetry_moves_labels_not_vertices(tmp_path):
    tracks = _tracks(tmp_path)
    windows = torch.arange(0, tracks.num_windows, 3)
    plain = tracks.batch(windows, np.random.default_rng(1))
    sym = tracks.batch(windows, np.random.default_rng(1), body_symmetry=True)
    # world positions of every node, every frame: unchanged
    assert torch.allclose(sym.history, plain.history, atol=1e-12)
    assert torch.allclose(sym.target, plain.target, atol=1e-12)
    # rest positions: relabelled for some graphs, and each graph's rest set is still the cube's
    changed = (sym.graph.rest - plain.graph.rest).norm(dim=-1) > 1e-9
    assert changed.any()
    for g in range(plain.graph.num_graphs):
        a = plain.graph.rest[plain.graph.node_graph == g]
        b = sym.graph.rest[sym.graph.node_graph == g]
        assert torch.cdist(b, a).amin(dim=1).max() < 1e-12
    # and the relabelled pose is a proper rotation that carries the new rest onto the vertices
    g = sym.graph
    for t in range(3):
        rot, _, proj = shape_match_packed(sym.history[:, t], g.rest, g.node_graph, g.num_graphs)
        assert torch.allclose(proj, sym.history[:, t], atol=1e-9)
        assert torch.allclose(torch.linalg.det(rot), torch.ones(g.num_graphs, dtype=rot.dtype))


def test_mirror_is_the_mirror_image_of_the_scene(tmp_path):
    tracks = _tracks(tmp_path)
    windows = torch.arange(0, tracks.num_windows, 2)
    plain = tracks.batch(windows, np.random.default_rng(3))
    mirrored = tracks.batch(windows, np.random.default_rng(3), mirror=True)
    m = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    # the flips are the generator's first draw (no rotation, no noise); one graph per window here
    flip = torch.from_numpy(np.random.default_rng(3).random(len(windows)) < 0.5)
    assert flip.any() and not flip.all()
    node_flip = flip[plain.graph.node_graph]
    for got, want in ((mirrored.history, plain.history), (mirrored.target, plain.target)):
        expect = torch.where(node_flip.view(-1, *[1] * (want.dim() - 1)), want * m, want)
        assert torch.allclose(got, expect, atol=1e-12)
    assert torch.allclose(mirrored.graph.rest, torch.where(node_flip[:, None], plain.graph.rest * m,
                                                           plain.graph.rest))
    # rigid and proper: the mirrored rest matches the mirrored vertices with a rotation (det +1)
    g = mirrored.graph
    rot, _, proj = shape_match_packed(mirrored.target, g.rest, g.node_graph, g.num_graphs)
    assert torch.allclose(proj, mirrored.target, atol=1e-9)
    assert (torch.linalg.det(rot) > 0).all()


def test_training_with_both_augmentations_runs(tmp_path):
    from gns.train import train
    from test_gns_train import quiet, tiny
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "run", tiny("train.steps=5", "valid.every=0", "augment.mirror=true",
                                      "augment.body_symmetry=true"), log=quiet)
    assert (tmp_path / "run" / "latest.pt").exists()


def test_body_frame_averaging_is_exactly_invariant_to_the_body_frame(tmp_path):
    """Relabelling a cube's rest positions by one of its symmetries (the same object in the same
    place) changes the plain prediction, not the body-frame-averaged one."""
    from dataclasses import replace

    from test_gns_train_levers import sim_and_batch

    from gns.symmetry import with_symmetries
    sim, b = sim_and_batch(tmp_path)
    g = with_symmetries(b.graph)
    assert (g.num_symmetries == 24).all()
    s = torch.from_numpy(mesh_symmetries(get_shape("cube").vertices)[7])
    relabelled = replace(g, rest=b.graph.rest @ s.T)
    for symmetrize in (False, True):
        sim.options = sim.options.replace(symmetrize=symmetrize, body_frames=True)
        a = sim.predict_acceleration(b.history, g)
        assert torch.allclose(sim.predict_acceleration(b.history, relabelled), a, atol=1e-6)
        sim.options = sim.options.replace(body_frames=False)   # control: without the averaging the labels matter
        assert not torch.allclose(sim.predict_acceleration(b.history, relabelled),
                                  sim.predict_acceleration(b.history, g), atol=1e-6)
    # a rollout builds the groups itself
    sim.options = sim.options.replace(symmetrize=True, body_frames=True)
    x = sim.rollout(b.history, b.graph, 2)
    assert torch.isfinite(x).all()
