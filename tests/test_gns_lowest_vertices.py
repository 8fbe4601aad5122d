"""The network sees only each object's vertices nearest the floor and its centre (features.lowest_vertices)."""
from dataclasses import replace

import numpy as np
import pytest
import torch
from gns_fixtures import rolled_out, write_toss_dataset

from datagen.scenes import get_shape
from gns.checkpoint import build_simulator
from gns.config import ConfigError
from gns.graph import MeshLibrary, lowest_nodes, select_nodes
from gns.geometry import shape_match_packed
from gns.spec import Floor, ModelSpec
from gns.checkpoint import read_checkpoint
from gns.train import train
from test_gns_train import quiet, tiny


def _graph(names=("sphere", "beveled_cube", "sphere")):
    meshes = {n: (get_shape(n).vertices, get_shape(n).faces) for n in set(names)}
    lib = MeshLibrary(meshes, centre_node=True, surface_edges=False)
    k = len(names)
    return lib.pack(lib.shape_ids(list(names)), torch.linspace(0.7, 1.4, k, dtype=torch.float64),
                    torch.full((k,), 0.4), torch.full((k,), 0.3))


def _turned(graph, seed=0):
    """Every object of graph at a random pose, 2 m above the floor (N, 3)."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(seed)
    rot = torch.from_numpy(Rotation.random(graph.num_graphs, random_state=seed).as_matrix())
    centre = torch.from_numpy(rng.uniform(-1, 1, (graph.num_graphs, 3)) + [0, 0, 2.0])
    return (rot[graph.node_graph] @ graph.rest[:, :, None])[..., 0] + centre[graph.node_graph]


def test_each_object_keeps_its_k_lowest_vertices_and_its_centre():
    graph = _graph()
    x = _turned(graph)
    keep = lowest_nodes(x[:, 2], graph, 5)
    count = torch.bincount(graph.node_graph).tolist()
    start = 0
    for n in count:
        z, kept = x[start:start + n, 2], keep[start:start + n]
        assert kept[-1]                                  # the centre node, last of its graph
        assert int(kept.sum()) == 6
        ring = z[:-1]
        assert set(torch.nonzero(kept[:-1])[:, 0].tolist()) == set(torch.argsort(ring)[:5].tolist())
        start += n
    # with the highest too: both ends of each object, and its centre
    both = lowest_nodes(x[:, 2], graph, 5, top=2)
    start = 0
    for n in count:
        ring, kept = x[start:start + n - 1, 2], both[start:start + n - 1]
        order = torch.argsort(ring).tolist()
        assert set(torch.nonzero(kept)[:, 0].tolist()) == set(order[:5] + order[-2:]) and both[start + n - 1]
        start += n
    # ties go to the lower index: a flat object keeps its first vertices
    assert lowest_nodes(torch.zeros(graph.num_nodes, dtype=torch.float64), graph, 3)[:3].all()


def test_the_selected_graph_keeps_the_spokes_of_the_kept_vertices_only():
    graph = _graph()
    x = _turned(graph, 1)
    sub, nodes = select_nodes(graph, lowest_nodes(x[:, 2], graph, 7))
    assert sub.num_graphs == graph.num_graphs and sub.num_nodes == 8 * graph.num_graphs
    torch.testing.assert_close(sub.rest, graph.rest[nodes])
    # every kept vertex joined both ways to its own centre, nothing else
    s, r = sub.mesh_edges.senders, sub.mesh_edges.receivers
    assert len(s) == 2 * 7 * graph.num_graphs
    assert torch.equal(sub.node_graph[s], sub.node_graph[r])
    centres = torch.cumsum(torch.bincount(sub.node_graph), 0) - 1
    assert bool(((s[:, None] == centres).any(1) ^ (r[:, None] == centres).any(1)).all())


def _simulator(k, floor=True, collisions=False, mode="vertex"):
    cfg = tiny(f"features.lowest_vertices={k}", "features.centre_node=true", "features.surface_edges=false",
               f"features.collision_mode={mode}")
    spec = ModelSpec(floor=Floor(z=0.0) if floor else None, frame_rate=12.0, gravity=(0.0, 0.0, -10.0),
                     collision_edges=collisions)
    torch.manual_seed(0)
    return build_simulator(cfg, spec)


def test_vertices_the_network_does_not_see_follow_the_pose_of_those_it_does():
    sim = _simulator(6).eval()
    graph = _graph()
    x_t = _turned(graph, 2)
    x_t[:, 2] -= 1.6          # near the floor, where it matters
    frames = [x_t - 0.02 * k for k in (2, 1, 0)]
    with torch.no_grad():
        x = sim.predict_next(*frames, graph)
        keep = lowest_nodes(x_t[:, 2], graph, 6)
        sub, nodes = select_nodes(graph, keep)
        alone = sim._predict_next(*(f[nodes] for f in frames), sub)
    # the seen nodes move as the network says, on a graph of them alone
    torch.testing.assert_close(x[nodes], alone)
    # the rest is rigid with the pose fitted to the seen ones, which a fit of all finds again
    rot, t, _ = shape_match_packed(alone, sub.rest, sub.node_graph, sub.num_graphs)
    rot_all, t_all, _ = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
    torch.testing.assert_close(rot_all, rot)
    torch.testing.assert_close(t_all, t)
    unseen = ~keep
    rigid = (rot[graph.node_graph] @ graph.rest[:, :, None])[..., 0] + t[graph.node_graph]
    torch.testing.assert_close(x[unseen], rigid[unseen])


def _rollout_equals_the_plain_loop(sim, x_t, graph, steps):
    """sim.rollout (free flight, sleep, fitted poses handed over) against advance + a shape match
    of every vertex at each step, from x_t moving at constant velocity."""
    history = torch.stack([x_t + torch.tensor([0.0, 0.01, 0.02 * k], dtype=torch.float64) for k in (2, 1, 0)], 1)
    with torch.no_grad():
        out, rots, trans = rolled_out(sim, history, graph, steps, free_flight=True, sleep=True, poses=True)
        frames = list(history.unbind(1))
        pose = [shape_match_packed(f, graph.rest, graph.node_graph, graph.num_graphs)[:2] for f in frames[-2:]]
        for step in range(steps):
            with sim.using(free_flight=True, sleep=True):
                x = sim.advance(frames, graph, pose)
            rot, t, matched = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
            torch.testing.assert_close(out[step], matched, atol=1e-9, rtol=0)
            torch.testing.assert_close(rots[step], rot, atol=1e-9, rtol=0)
            torch.testing.assert_close(trans[step], t, atol=1e-9, rtol=0)
            frames.append(out[step])   # the rollout's own frames: differences do not compound here
            pose = [pose[1], (rots[step], trans[step])]
    assert sim.rollout_counts["network"] > 0


@pytest.mark.parametrize("heights", [(0.4, 0.5, 0.45), (0.4, 3.0, 3.5)])
def test_a_rollout_takes_the_fitted_poses_as_a_second_fit_would_find_them(heights):
    """Rollouts reuse the pose fitted to the seen nodes (and the ballistic and kept ones) instead of
    shape matching every vertex again: the same frames and poses as the plain loop. All objects
    near the floor, then two of three in free flight (the network on a subgraph)."""
    sim = _simulator(6).eval()
    graph = _graph()
    x_t = _turned(graph, 4)
    centres = torch.tensor(heights, dtype=torch.float64)
    lift = centres - torch.zeros(3, dtype=torch.float64).index_add_(0, graph.node_graph, x_t[:, 2]) / torch.bincount(
        graph.node_graph)
    x_t[:, 2] += lift[graph.node_graph]
    _rollout_equals_the_plain_loop(sim, x_t, graph, 5)
    if heights[1] > 1:
        assert sim.rollout_counts["free_flight"] > 0


def test_the_loss_counts_the_seen_nodes_only():
    sim = _simulator(4).train()
    graph = _graph()
    x_t = _turned(graph, 3)
    history = torch.stack([x_t - 0.04, x_t - 0.02, x_t], 1)
    target = x_t + 0.01
    loss = sim.loss(history, target, graph)
    sub, nodes = select_nodes(graph, lowest_nodes(x_t[:, 2], graph, 4))
    sim.lowest_vertices = 0
    torch.testing.assert_close(loss, sim.loss(history[nodes], target[nodes], sub))
    # and a target moved on an unseen vertex does not change it
    moved = target.clone()
    moved[~lowest_nodes(x_t[:, 2], graph, 4)] += 1.0
    sim.lowest_vertices = 4
    torch.testing.assert_close(sim.loss(history, moved, graph), loss)


def test_bad_settings_are_one_clear_error():
    with pytest.raises(ConfigError, match="lowest_vertices must be 0"):
        tiny("features.lowest_vertices=2", "features.centre_node=true")
    with pytest.raises(ConfigError, match="needs features.centre_node"):
        tiny("features.lowest_vertices=8")
    with pytest.raises(ValueError, match="lowest_vertices needs a floor"):
        _simulator(8, floor=False)
    assert _simulator(8, collisions=True).layout.collisions


def _stacked_scene():
    """Scene 0: a sphere on the floor, a beveled cube whose lowest vertex is 5 cm above the
    sphere's top (their contact far above the cube's lowest vertices) and a cube 3 away; scene 1:
    a sphere alone. Positions at t (N, 3) and the graph."""
    names = ("sphere", "beveled_cube", "beveled_cube", "sphere")
    meshes = {n: (get_shape(n).vertices, get_shape(n).faces) for n in set(names)}
    lib = MeshLibrary(meshes, centre_node=True, surface_edges=False)
    graph = lib.pack(lib.shape_ids(list(names)), torch.tensor([1.4, 1.0, 1.0, 0.7], dtype=torch.float64),
                     torch.full((4,), 0.4), torch.full((4,), 0.3), graph_scene=torch.tensor([0, 0, 0, 1]))
    rest = [graph.rest[graph.node_graph == g] for g in range(4)]
    centre = torch.zeros(4, 3, dtype=torch.float64)
    for g, x in ((0, 0.0), (2, 3.0), (3, 0.0)):
        centre[g] = torch.tensor([x, 0.0, -float(rest[g][:, 2].min()) + (0.5 if g == 3 else 0.0)])
    # the cube's lowest vertex 5 cm above the sphere's highest: inside the collision radius
    top = rest[0][rest[0][:, 2].argmax()] + centre[0]
    centre[1] = top - rest[1][rest[1][:, 2].argmin()] + torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64)
    return graph.rest + centre[graph.node_graph], graph


def test_with_other_objects_every_vertex_in_contact_is_seen():
    """Low graphs in scenes of several objects: the network also sees each vertex that has a
    collision edge (however high), the cut graph carries every collision edge of the whole one,
    and the kept nodes move exactly as the network says on that graph."""
    from gns.contacts import collision_edges
    sim = _simulator(6, collisions=True).eval()
    x_t, graph = _stacked_scene()
    full = collision_edges(x_t, graph, sim.layout.collision_radius)
    assert len(full.senders) > 0
    touching = torch.zeros(graph.num_nodes, dtype=torch.bool)
    touching[full.senders] = True
    low = lowest_nodes(x_t[:, 2], graph, 6)
    assert bool((touching & ~low).any())              # contacts the floor rule alone would miss
    sub, nodes = sim.network_nodes(x_t, graph)
    seen = torch.zeros(graph.num_nodes, dtype=torch.bool)
    seen[nodes] = True
    assert torch.equal(seen, low | touching)
    pairs = lambda s, r: sorted(zip(s.tolist(), r.tolist()))  # noqa: E731
    assert pairs(nodes[sub.collision_edges.senders], nodes[sub.collision_edges.receivers]) == \
        pairs(full.senders, full.receivers)
    # the same edges again from the cut graph's own positions: nothing depends on the handover
    again = collision_edges(x_t[nodes], replace(sub, collision_edges=None), sim.layout.collision_radius)
    assert pairs(again.senders, again.receivers) == pairs(sub.collision_edges.senders, sub.collision_edges.receivers)
    frames = [x_t - torch.tensor([0.0, 0.0, 0.02 * k], dtype=torch.float64) for k in (2, 1, 0)]
    with torch.no_grad():
        x = sim.predict_next(*frames, graph)
        alone = sim._predict_next(*(f[nodes] for f in frames), replace(sub, collision_edges=None))
    torch.testing.assert_close(x[nodes], alone)
    rot, t, _ = shape_match_packed(alone, sub.rest, sub.node_graph, sub.num_graphs)
    rigid = (rot[graph.node_graph] @ graph.rest[:, :, None])[..., 0] + t[graph.node_graph]
    torch.testing.assert_close(x[~seen], rigid[~seen])


def test_with_other_objects_a_rollout_takes_the_fitted_poses_too():
    sim = _simulator(6, collisions=True).eval()
    x_t, graph = _stacked_scene()
    _rollout_equals_the_plain_loop(sim, x_t, graph, 4)


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_trains_on_its_lowest_vertices_and_rolls_out(tmp_path):
    import gns
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=2", "features.normalizer_steps=2", "features.centre_node=true",
             "features.surface_edges=false")
    train(data, tmp_path / "full", tiny(*small), log=quiet)
    # a fine-tune may change it (the weights keep their shapes)
    train(data, tmp_path / "low", tiny(*small, "features.lowest_vertices=4", f"train.init_from={tmp_path / 'full'}"),
          log=quiet)
    assert read_checkpoint(tmp_path / "low" / "latest.pt")["config"]["features"]["lowest_vertices"] == 4
    model = gns.load(tmp_path / "low")
    assert model.simulator.lowest_vertices == 4
    out = model.rollout(["cube"], [[0.0, 0.0, 0.6]], [[1.0, 0.0, 0.0, 0.0]], velocities=[[1.0, 0.0, -1.0]], steps=4)
    assert torch.isfinite(out.positions).all()


def test_an_ensemble_must_see_the_same_nodes():
    with pytest.raises(ValueError, match="nodes seen"):
        _simulator(6).set_ensemble([_simulator(8)])
    _simulator(6).set_ensemble([_simulator(6)])


def test_surface_edges_on_low_graphs_are_those_of_the_whole_graph_and_mirror_exactly():
    """Vertex-to-surface edges need the other object's triangles, which a cut graph loses: they are
    built on the whole graph, and the cut graph carries them (both ends kept, vectors as they were);
    a mirror-averaged step (symmetrize d1) maps those vectors rather than building edges again."""
    from gns.contacts import surface_edges
    sim = _simulator(6, collisions=True, mode="surface").eval()
    x_t, graph = _stacked_scene()
    full = surface_edges(x_t, graph, sim.layout.collision_radius)
    assert len(full.senders) > 0
    sub, nodes = sim.network_nodes(x_t, graph)
    got = sorted(zip(nodes[sub.collision_edges.senders].tolist(), nodes[sub.collision_edges.receivers].tolist(),
                     sub.collision_edges.vectors.tolist()))
    assert got == sorted(zip(full.senders.tolist(), full.receivers.tolist(), full.vectors.tolist()))
    frames = [x_t - torch.tensor([0.01 * k, 0.0, 0.02 * k], dtype=torch.float64) for k in (2, 1, 0)]
    history = torch.stack(frames, dim=1)
    g = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    sim.options = sim.options.replace(symmetrize="d1")
    with torch.no_grad():
        a = sim.predict_acceleration(history, graph)
        m = sim.predict_acceleration(history @ g.T, replace(graph, rest=graph.rest @ g.T))
        x = sim.predict_next(*frames, graph)
        xm = sim.predict_next(*(f @ g.T for f in frames), replace(graph, rest=graph.rest @ g.T))
    assert float((m - a @ g.T).abs().max() / a.abs().max()) < 1e-5
    torch.testing.assert_close(xm, x @ g.T, rtol=0, atol=1e-6)


def test_objects_alone_in_their_scenes_roll_out_as_when_each_step_looks_for_contacts(monkeypatch):
    """A batch whose scenes hold one object each (single-object scenes rolled out by a model of
    several) has no collision edge, swept box or overlap to find: the rollout drops the grouping
    and no step looks for them, with the same frames and poses to the last bit as when every
    step does. The objects overlap in space: scenes apart never meet either way."""
    import gns.contacts
    import gns.stepping
    sim = _simulator(6, collisions=True).eval()
    graph = replace(_graph(), graph_scene=torch.arange(3))
    x_t = _turned(graph, 4)
    lift = torch.tensor([0.4, 3.0, 0.45], dtype=torch.float64) - torch.zeros(3, dtype=torch.float64).index_add_(
        0, graph.node_graph, x_t[:, 2]) / torch.bincount(graph.node_graph)
    x_t[:, 2] += lift[graph.node_graph]
    history = torch.stack([x_t + torch.tensor([0.0, 0.01, 0.02 * k], dtype=torch.float64) for k in (2, 1, 0)], 1)
    searches = []
    pairs = gns.contacts.candidate_pairs   # where every search (edges, swept boxes, overlaps) starts
    monkeypatch.setattr(gns.contacts, "candidate_pairs", lambda g: searches.append(1) or pairs(g))
    options = dict(free_flight=True, keep_apart=True, poses=True)
    skipped = rolled_out(sim, history, graph, 5, **options)
    assert not searches and sim.rollout_counts["network"] > 0 and sim.rollout_counts["free_flight"] > 0
    monkeypatch.setattr(gns.stepping, "alone_in_scenes", lambda g: False)
    searched = rolled_out(sim, history, graph, 5, **options)
    assert searches
    for a, b in zip(skipped, searched):
        assert torch.equal(a, b)
