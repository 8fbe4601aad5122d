"""Face-face collision edges (gns.face_contacts, features.collision_mode = "face")."""
import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes

from gns.contacts import surface_edges
from gns.data import vertices_from_poses
from gns.face_contacts import closest_points_on_triangles, face_edges
from gns.graph import MeshLibrary
from gns.triangles import closest_points_on_segments, columns, rows

DTYPE = torch.float64


def _samples_on_triangles(t, rng, n):
    u = torch.from_numpy(rng.uniform(size=(len(t), n, 2)))
    u = torch.where(u.sum(-1, keepdim=True) > 1, 1 - u, u)
    return t[:, None, 0] + u[..., :1] * (t[:, None, 1] - t[:, None, 0]) + u[..., 1:] * (t[:, None, 2] - t[:, None, 0])


def test_closest_points_on_segments_are_the_nearest_of_dense_samples():
    rng = np.random.default_rng(1)
    m = 400
    p1, q1, p2, q2 = (torch.from_numpy(rng.normal(size=(m, 3))) for _ in range(4))
    q2[:50] = p2[:50] + (q1[:50] - p1[:50]) * 0.7        # parallel segments too
    a, b = (rows(v) for v in closest_points_on_segments(*(columns(v) for v in (p1, q1, p2, q2))))
    s = torch.linspace(0, 1, 801, dtype=DTYPE)
    on1 = p1[:, None] + s[None, :, None] * (q1 - p1)[:, None]
    on2 = p2[:, None] + s[None, :, None] * (q2 - p2)[:, None]
    brute = torch.cdist(on1, on2).flatten(1).min(dim=1).values
    mine = (a - b).norm(dim=-1)
    assert (mine <= brute + 1e-9).all() and (brute - mine).max() < 0.01


def test_closest_points_on_triangles_are_the_nearest_of_dense_samples():
    rng = np.random.default_rng(2)
    m = 200
    t1 = torch.from_numpy(rng.normal(size=(m, 3, 3)))
    t2 = torch.from_numpy(rng.normal(size=(m, 3, 3))) + torch.from_numpy(rng.normal(size=(m, 1, 3))) * 3
    p1, p2 = closest_points_on_triangles(t1, t2)
    s1, s2 = _samples_on_triangles(t1, rng, 1500), _samples_on_triangles(t2, rng, 1500)
    brute = torch.cdist(s1, s2).flatten(1).min(dim=1).values
    mine = (p1 - p2).norm(dim=-1)
    assert (brute < 0.02).sum() >= 5      # some pairs cross: they meet where an edge passes through
    assert (mine <= brute + 1e-9).all() and (brute - mine).max() < 0.2   # samples 1500 a triangle
    # the points lie on their triangles: the same distance to them as to themselves
    from gns.contacts import closest_point_on_triangle
    for p, t in ((p1, t1), (p2, t2)):
        assert torch.allclose(closest_point_on_triangle(p, t[:, 0], t[:, 1], t[:, 2]), p, atol=1e-9)


def _crossed_cubes(gap, turn=0.0, shift=(0.0, 0.0)):
    """Two unit cubes edge on edge: the lower turned 45 degrees about x (its top an edge along x),
    the upper 45 degrees about y (its bottom an edge along y), `gap` between the edges, the upper
    moved by `shift` in x and y; the scene turned by `turn` about z."""
    lib = MeshLibrary(cube_meshes())
    graph = lib.pack(lib.shape_ids(["cube", "cube"]), torch.ones(2, dtype=DTYPE), torch.full((2,), 0.4),
                     torch.full((2,), 0.3), torch.zeros(2, dtype=torch.int64))
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    rx = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=DTYPE)
    ry = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=DTYPE)
    rz = torch.tensor([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]], dtype=DTYPE)
    pos = torch.tensor([[[0.0, 0.0, 0.0]], [[*shift, 2 ** 0.5 + gap]]], dtype=DTYPE) @ rz.T
    rot = torch.stack([rz @ rx, rz @ ry])[:, None]
    return graph, vertices_from_poses(graph, pos, rot)[:, 0], rz


@pytest.mark.parametrize("gap", [0.1, 0.02])
def test_edge_on_edge_contact_is_seen_by_face_edges_not_by_surface_edges(gap):
    graph, x, _ = _crossed_cubes(gap)
    # every vertex is ~0.35 from the other cube: vertex-to-surface edges within 0.15 see nothing
    assert len(surface_edges(x, graph, 0.15).senders) == 0
    e = face_edges(x, graph, 0.15)
    objects = {(int(graph.node_graph[s]), int(graph.node_graph[r])) for s, r in zip(e.senders, e.receivers)}
    assert objects == {(0, 1), (1, 0)}
    # the contact is between the two edges, at the true gap, along z, at the crossing point
    assert torch.allclose(e.signed.abs().min(), torch.tensor(gap, dtype=DTYPE), atol=1e-12)
    assert torch.allclose(e.vectors[:, :3].norm(dim=-1), e.signed[:, 0].abs(), atol=1e-12)
    contact = graph.node_graph[e.receivers] == 1
    p_r = x[e.receivers] - e.vectors[:, 3:6]
    assert torch.allclose(p_r[contact], torch.tensor([[0.0, 0.0, 2 ** 0.5 / 2 + gap]], dtype=DTYPE).expand(int(contact.sum()), 3), atol=1e-9)
    # the vertices of the faces at the edge all hear of it, each at most once from the other cube
    pairs = set(zip(e.receivers.tolist(), graph.node_graph[e.senders].tolist()))
    assert len(pairs) == len(e.receivers) and len(e.receivers) >= 8


def test_face_edges_turn_with_the_scene_and_ignore_translation():
    # off the edges' midpoints: the nearest vertex of the sending face (the sender) is then unique
    graph, x, _ = _crossed_cubes(0.05, shift=(0.13, -0.21))
    e0 = face_edges(x, graph, 0.15)
    graph, y, rz = _crossed_cubes(0.05, turn=0.7, shift=(0.13, -0.21))
    e1 = face_edges(y + torch.tensor([5.0, -3.0, 0.0], dtype=DTYPE), graph, 0.15)
    key0 = torch.argsort(e0.receivers * 1000 + e0.senders)
    key1 = torch.argsort(e1.receivers * 1000 + e1.senders)
    assert torch.equal(e0.receivers[key0], e1.receivers[key1]) and torch.equal(e0.senders[key0], e1.senders[key1])
    turned = (e0.vectors[key0].view(-1, 2, 3) @ rz.T).reshape(-1, 6)
    assert torch.allclose(turned, e1.vectors[key1], atol=1e-9)
    assert torch.allclose(e0.signed[key0], e1.signed[key1], atol=1e-12)


def test_objects_apart_get_no_face_edges_and_crossing_faces_meet_at_distance_zero():
    graph, x, _ = _crossed_cubes(0.3)
    assert len(face_edges(x, graph, 0.15).senders) == 0
    graph, x, _ = _crossed_cubes(-0.05)
    e = face_edges(x, graph, 0.15)
    assert set(graph.node_graph[e.receivers].tolist()) == {0, 1}
    assert float(e.signed.abs().min()) == 0.0 and torch.equal(e.vectors[:, :3].norm(dim=-1), e.signed[:, 0].abs())


def test_face_edge_geometry_carries_the_gradient_of_the_positions():
    graph, x, _ = _crossed_cubes(0.05)
    plain = face_edges(x, graph, 0.15)
    x = x.clone().requires_grad_()
    e = face_edges(x, graph, 0.15)
    assert torch.equal(e.vectors, plain.vectors) and torch.equal(e.signed, plain.signed)
    e.signed.sum().backward()
    upper = graph.node_graph == 1
    # the upper cube moving up opens the gap, the lower one moving up closes it
    assert torch.isfinite(x.grad).all() and x.grad[upper, 2].sum() > 0 and x.grad[~upper, 2].sum() < 0


def _random_triangle_pairs(m=400, seed=3):
    rng = np.random.default_rng(seed)
    t1 = torch.from_numpy(rng.normal(size=(m, 3, 3)))
    return t1, torch.from_numpy(rng.normal(size=(m, 3, 3))) + torch.from_numpy(rng.normal(size=(m, 1, 3))) * 2


def test_the_plane_test_rules_out_only_triangles_beyond_the_radius():
    from gns.face_contacts import _beyond_plane, _distance
    t1, t2 = _random_triangle_pairs()
    dist = _distance(t1, t2)
    for radius in (0.1, 0.5, 1.0):
        apart = _beyond_plane(t1, t2, radius) | _beyond_plane(t2, t1, radius)
        assert apart.any() and not (apart & (dist < radius)).any()
    flat = t1.clone()
    flat[:, 2] = flat[:, 1]            # no plane: nothing ruled out
    assert not _beyond_plane(flat, t2, 0.1).any()


def test_compiled_triangle_distances_are_the_eager_ones_to_rounding():
    from gns.face_contacts import _distance, compiled_distance
    t1, t2 = _random_triangle_pairs()
    eager = _distance(t1, t2)
    assert (eager == 0).sum() >= 5       # crossing pairs among them
    assert torch.allclose(compiled_distance()(t1, t2), eager, rtol=0, atol=1e-12)
    graph, x, _ = _crossed_cubes(0.05, shift=(0.13, -0.21))
    e, c = face_edges(x, graph, 0.15), face_edges(x, graph, 0.15, compiled=True)
    assert torch.equal(e.senders, c.senders) and torch.equal(e.receivers, c.receivers)
    assert torch.allclose(e.vectors, c.vectors, atol=1e-12)


@pytest.mark.parametrize("steps", [10, 500])
def test_long_face_edge_trainings_measure_through_the_compiled_distances(monkeypatch, steps):
    # a training of hundreds of steps repays the distances' compile, a short one (as here in tests) not
    import gns
    import gns.face_contacts
    from gns.config import build_config
    from gns.run_folder import World
    from gns.train import CONTACTS_COMPILE_STEPS, _place_model
    asked = []
    monkeypatch.setattr(gns.face_contacts, "face_edges", lambda x, graph, radius, compiled: asked.append(compiled))
    sim = gns.load("movi_a_multi").simulator
    _place_model(sim, build_config(), torch.device("cpu"), World(), steps)
    graph, x, _ = _crossed_cubes(0.05)
    sim.collision_edges(x, graph)
    assert asked == [steps >= CONTACTS_COMPILE_STEPS]


def _crowd(seed=5, scenes=2, objects=4, offset=0.0):
    """Random poses of MOVi-A's shapes, `objects` a scene packed within ~1.5 of each other (many
    object pairs within the radius, some overlapping), the scenes `offset` apart along x."""
    from datagen.scenes import get_shape
    names = ["beveled_cube", "cylinder", "sphere"]
    lib = MeshLibrary({n: (get_shape(n).vertices, get_shape(n).faces) for n in names})
    rng = np.random.default_rng(seed)
    count = scenes * objects
    graph = lib.pack(lib.shape_ids([names[i] for i in rng.integers(0, 3, count)]),
                     torch.from_numpy(rng.choice([0.7, 1.4], count)), torch.full((count,), 0.4),
                     torch.full((count,), 0.3), torch.arange(scenes).repeat_interleave(objects))
    from gns.geometry import quat_from_axis_angle, quat_to_matrix
    pos = torch.from_numpy(rng.uniform(-0.8, 0.8, (count, 1, 3))) + offset
    pos[:, 0, 0] += 5.0 * torch.arange(scenes).repeat_interleave(objects)
    rot = torch.stack([torch.from_numpy(quat_to_matrix(quat_from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi))))
                       for _ in range(count)])[:, None]
    return graph, vertices_from_poses(graph, pos, rot)[:, 0]


def _closest_by_brute_force(x, graph):
    """Per (receiving vertex, sending object) of the same scene: the smallest distance between a
    face at the vertex and a face of the object, every face pair measured in float64."""
    faces, owner = graph.faces, graph.node_graph[graph.faces[:, 0]]
    best = {}
    for a in range(graph.num_graphs):
        for b in range(graph.num_graphs):
            if a == b or graph.graph_scene[a] != graph.graph_scene[b]:
                continue
            fa, fb = (owner == a).nonzero()[:, 0], (owner == b).nonzero()[:, 0]
            i, j = fa.repeat_interleave(len(fb)), fb.repeat(len(fa))
            p, q = closest_points_on_triangles(x[faces[i]], x[faces[j]])
            dist = (p - q).norm(dim=-1).repeat(3)
            v = faces[i].T.reshape(-1)                   # each pair at each corner of its receiving face
            low = torch.full((len(x),), torch.inf, dtype=DTYPE).scatter_reduce(0, v, dist, "amin")
            best.update({(node, b): float(low[node]) for node in v.unique().tolist()})
    return best


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_face_edges_are_the_closest_face_pairs_of_a_brute_force_search(offset):
    # the search's culls (bounds, the other object's sphere, planes) and its float32 choice of
    # pairs lose no pair within the radius and keep each vertex's closest, wherever the scene is
    radius = 0.25
    graph, x = _crowd(offset=offset)
    truth = _closest_by_brute_force(x, graph)
    e = face_edges(x, graph, radius)
    found = {(int(r), int(graph.node_graph[s])): float(d) for r, s, d in zip(e.receivers, e.senders, e.signed[:, 0].abs())}
    near = {k for k, d in truth.items() if d < radius - 1e-6}
    assert len(near) >= 50 and any(truth[k] == 0 for k in near)        # a crowd, objects crossing too
    assert near <= set(found) and set(found) <= {k for k, d in truth.items() if d < radius + 1e-6}
    assert max(abs(found[k] - truth[k]) for k in found) < 1e-5 * max(1.0, offset)
    for r, s in zip(e.receivers, e.senders):          # one edge per vertex and other object
        assert graph.node_graph[r] != graph.node_graph[s]
    assert len(found) == len(e.receivers)


def test_smallest_per_group_takes_the_first_of_equal_values():
    from gns.contacts import smallest_per_group
    group = torch.tensor([7, 3, 7, 3, 9, 7, 3])
    value = torch.tensor([2.0, 1.0, 1.0, 1.0, float("nan"), 1.0, 5.0])
    assert smallest_per_group(group, value).tolist() == [1, 2, 4]         # groups 3, 7, 9 in order
    dense = torch.tensor([1, 0, 1, 0])
    assert smallest_per_group(dense, torch.tensor([3.0, 2.0, 3.0, 4.0]), size=2).tolist() == [1, 0]
    assert smallest_per_group(torch.zeros(0, dtype=torch.int64), torch.zeros(0)).tolist() == []
