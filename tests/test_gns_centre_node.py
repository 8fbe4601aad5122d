"""A node at each object's centre of mass joined to all its vertices (features.centre_node)."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import shortest_path
from gns_fixtures import write_toss_dataset

import gns
from datagen.scenes import get_shape
from gns.checkpoint import build_simulator
from gns.fine_tune import init_from
from gns.graph import MeshLibrary, centre_spokes
from gns.geometry import shape_match_packed
from gns.spec import ModelSpec
from gns.checkpoint import CheckpointError, read_checkpoint
from gns.train import train
from test_gns_train import quiet, tiny


def _hops(graph) -> np.ndarray:
    n = graph.num_nodes
    s, r = graph.mesh_edges.senders.numpy(), graph.mesh_edges.receivers.numpy()
    return shortest_path(sp.csr_matrix((np.ones(len(s)), (s, r)), shape=(n, n)), unweighted=True)


@pytest.mark.parametrize("shape", ["sphere", "beveled_cube"])
def test_every_vertex_is_two_steps_from_every_other_through_the_centre(shape):
    mesh = get_shape(shape)
    plain = MeshLibrary({"m": (mesh.vertices, mesh.faces)})
    centred = MeshLibrary({"m": (mesh.vertices, mesh.faces)}, centre_node=True)
    args = (torch.tensor([1.4]), torch.tensor([0.4]), torch.tensor([0.3]))
    g0, g1 = plain.pack(plain.shape_ids(["m"]), *args), centred.pack(centred.shape_ids(["m"]), *args)
    n = len(mesh.vertices)
    # the mesh alone is 6 edges across, more than the gns_cpu preset's 5 message-passing steps
    assert _hops(g0).max() == 6
    assert g1.num_nodes == n + 1 and _hops(g1).max() == 2
    # the centre is the centre of mass (rest position 0), the vertices are unchanged
    assert torch.equal(g1.rest[n], torch.zeros(3, dtype=torch.float64))
    assert torch.equal(g1.rest[:n], g0.rest)
    # spokes both ways, once each; mesh edges as before; the faces (surface contacts) untouched
    assert g1.mesh_edges.senders.numel() == g0.mesh_edges.senders.numel() + 2 * n
    assert torch.equal(g1.faces, g0.faces)
    spokes = centre_spokes(n)
    assert len(np.unique(spokes, axis=0)) == 2 * n and set(spokes[spokes[:, 0] == n][:, 1]) == set(range(n))


def test_shape_matching_with_the_centre_node_recovers_the_pose():
    mesh = get_shape("cylinder")
    lib = MeshLibrary({"c": (mesh.vertices, mesh.faces)}, centre_node=True)
    graph = lib.pack(lib.shape_ids(["c", "c"]), torch.tensor([0.7, 1.4]), torch.tensor([0.4, 0.4]),
                     torch.tensor([0.3, 0.3]))
    angle = 1.1
    rot = torch.tensor([[1.0, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]],
                       dtype=torch.float64)
    centre = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    x = graph.rest @ rot.T + centre
    r, t, _ = shape_match_packed(x, graph.rest, graph.node_graph, 2)
    torch.testing.assert_close(r, rot.expand(2, 3, 3))
    torch.testing.assert_close(t, centre.expand(2, 3))


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_is_fine_tuned_with_a_centre_node_and_rolls_out_with_it(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "plain", tiny(*small), log=quiet)
    # the centre node adds nodes and edges, not parameters: a model without it starts one with it
    train(data, tmp_path / "centre", tiny(*small, "features.centre_node=true",
                                          f"train.init_from={tmp_path / 'plain'}"), log=quiet)
    plain, centre = read_checkpoint(tmp_path / "plain" / "latest.pt"), read_checkpoint(tmp_path / "centre" / "latest.pt")
    assert centre["config"]["features"]["centre_node"] is True
    assert {k: v.shape for k, v in plain["model"].items()} == {k: v.shape for k, v in centre["model"].items()}
    model = gns.load(tmp_path / "centre")
    assert model.simulator.centre_node
    out = model.rollout(["cube"], [[0.0, 0.0, 2.0]], [[1.0, 0.0, 0.0, 0.0]], velocities=[[1.0, 0.0, 0.0]], steps=3)
    # the network's graph: 8 cube vertices and the centre, which follows the centre of mass
    assert out.vertices.shape[1] == 9 and torch.isfinite(out.positions).all()
    torch.testing.assert_close(out.vertices[:, 8], out.positions[:, 0].to(out.vertices.dtype))
    # a resumed run must keep the graphs it trained on
    with pytest.raises(CheckpointError, match="centre_node"):
        train(data, tmp_path / "centre", tiny("train.steps=8", "valid.every=0", "features.normalizer_steps=2"),
              resume=True, log=quiet)
    # and an ensemble reads one kind of graph
    with pytest.raises(ValueError, match="centre_node"):
        model.simulator.set_ensemble([gns.load(tmp_path / "plain").simulator])


def test_fine_tuning_may_repeat_the_processor_more_often_resuming_may_not(tmp_path):
    # K (model.processor_repeats) applies the same L blocks again: the weights keep their shapes
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "k1", tiny(*small), log=quiet)
    train(data, tmp_path / "k2", tiny(*small, "model.processor_repeats=2", f"train.init_from={tmp_path / 'k1'}"),
          log=quiet)
    k1, k2 = read_checkpoint(tmp_path / "k1" / "latest.pt"), read_checkpoint(tmp_path / "k2" / "latest.pt")
    assert k2["config"]["model"]["processor_repeats"] == 2
    assert {k: v.shape for k, v in k1["model"].items()} == {k: v.shape for k, v in k2["model"].items()}
    assert gns.load(tmp_path / "k2").simulator.network.processor_repeats == 2
    with pytest.raises(CheckpointError, match="processor_repeats"):
        train(data, tmp_path / "k2", tiny("train.steps=8", "valid.every=0", "features.normalizer_steps=2"),
              resume=True, log=quiet)
    # the message passing steps L are weights: a fine-tune may only untie them into a multiple
    with pytest.raises(CheckpointError, match="message_passing_steps is 2 in the checkpoint, 3 now"):
        train(data, tmp_path / "l3", tiny(*small, "model.message_passing_steps=3", f"train.init_from={tmp_path / 'k1'}"),
              log=quiet)


def test_untying_a_repeated_processor_starts_from_the_same_function(tmp_path):
    # L = 2 blocks applied K = 2 times become L = 4 blocks of their own, each a copy of block i mod 2
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "k2", tiny("train.steps=6", *small, "model.processor_repeats=2"), log=quiet)
    cfg = tiny(*small, "model.message_passing_steps=4", f"train.init_from={tmp_path / 'k2'}")
    spec = ModelSpec.from_dict(read_checkpoint(tmp_path / "k2" / "latest.pt")["spec"])
    untied = build_simulator(cfg, spec)
    init_from(untied, cfg.train.init_from, cfg, spec)
    tied = gns.load(tmp_path / "k2").simulator
    assert len(untied.network.blocks) == 4 and untied.network.processor_repeats == 1
    for i, block in enumerate(untied.network.blocks):
        for (name, a), b in zip(block.state_dict().items(), tied.network.blocks[i % 2].state_dict().values()):
            assert torch.equal(a, b), name
    nodes = torch.randn(7, tied.network.node_encoder[0].in_features)
    edges = torch.randn(9, tied.network.edge_encoder[0].in_features)
    args = (nodes, edges, torch.randint(0, 7, (9,)), torch.randint(0, 7, (9,)))
    torch.testing.assert_close(untied.network(*args), tied.network(*args), rtol=0, atol=0)
    # and the copies then train apart
    train(data, tmp_path / "l4b", tiny("train.steps=6", *small, "model.message_passing_steps=4",
                                       f"train.init_from={tmp_path / 'k2'}"), log=quiet)
    trained = gns.load(tmp_path / "l4b").simulator.network.blocks
    assert not torch.equal(trained[0].node_mlp[0].weight, trained[2].node_mlp[0].weight)


@pytest.mark.parametrize("shape", ["sphere", "beveled_cube"])
def test_spokes_only_graphs_keep_the_centre_and_drop_every_surface_edge(shape):
    mesh = get_shape(shape)
    centred = MeshLibrary({"m": (mesh.vertices, mesh.faces)}, centre_node=True)
    spokes = MeshLibrary({"m": (mesh.vertices, mesh.faces)}, centre_node=True, surface_edges=False)
    args = (torch.tensor([1.4]), torch.tensor([0.4]), torch.tensor([0.3]))
    g1, g2 = centred.pack(centred.shape_ids(["m"]), *args), spokes.pack(spokes.shape_ids(["m"]), *args)
    n = len(mesh.vertices)
    # the same nodes, 2 steps across, and only the 2n spokes: a fraction of the edges the network works on
    assert g2.num_nodes == g1.num_nodes == n + 1 and _hops(g2).max() == 2
    assert torch.equal(g2.rest, g1.rest) and torch.equal(g2.faces, g1.faces)
    s, r = g2.mesh_edges.senders, g2.mesh_edges.receivers
    assert s.numel() == 2 * n and bool(((s == n) ^ (r == n)).all())
    assert g1.mesh_edges.senders.numel() > 3 * s.numel()
    with pytest.raises(ValueError, match="centre node"):
        MeshLibrary({"m": (mesh.vertices, mesh.faces)}, surface_edges=False)


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_centred_model_is_fine_tuned_onto_spokes_only_and_keeps_them(tmp_path):
    from gns.config import ConfigError
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2", "features.centre_node=true")
    train(data, tmp_path / "centre", tiny(*small), log=quiet)
    train(data, tmp_path / "spokes", tiny(*small, "features.surface_edges=false",
                                          f"train.init_from={tmp_path / 'centre'}"), log=quiet)
    assert read_checkpoint(tmp_path / "spokes" / "latest.pt")["config"]["features"]["surface_edges"] is False
    model = gns.load(tmp_path / "spokes")
    out = model.rollout(["cube"], [[0.0, 0.0, 2.0]], [[1.0, 0.0, 0.0, 0.0]], velocities=[[1.0, 0.0, 0.0]], steps=3)
    assert out.vertices.shape[1] == 9 and torch.isfinite(out.positions).all()
    with pytest.raises(CheckpointError, match="surface_edges"):
        train(data, tmp_path / "spokes", tiny(*small, "train.steps=8"), resume=True, log=quiet)
    # an ensemble may mix the two (each member reads its own mesh edges; test_gns_train_levers.py),
    # not a model without the centre nodes the spokes need
    model.simulator.set_ensemble([gns.load(tmp_path / "centre").simulator])
    train(data, tmp_path / "plain", tiny("train.steps=4", "valid.every=0", "features.normalizer_steps=2"), log=quiet)
    with pytest.raises(ValueError, match="centre_node"):
        model.simulator.set_ensemble([gns.load(tmp_path / "plain").simulator])
    # spokes need a centre: one clear line, before any training
    with pytest.raises(ConfigError, match="surface_edges=false needs features.centre_node"):
        train(data, tmp_path / "bad", tiny("train.steps=4", "features.surface_edges=false"), log=quiet)

