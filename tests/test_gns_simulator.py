"""Integrator, normalisers, features, translation equivariance and shape matching."""
import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes

from gns.config import FeatureConfig, ModelConfig
from gns.data import vertices_from_poses
from gns.network import Normalizer, raw_node_features
from gns.geometry import quat_to_matrix
from gns.graph import MeshLibrary
from gns.geometry import acceleration_of, integrate, shape_match, shape_match_packed
from gns.simulator import LearnedSimulator
from gns.spec import Floor, ModelSpec

SPEC = ModelSpec(floor=Floor(0.0), materials_vary=False)
DTYPE = torch.float64


def random_rotations(n, seed):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return torch.from_numpy(quat_to_matrix(q))


def cube_batch(num_graphs=3, seed=0):
    """A packed batch of cubes with random poses: graph and history (N, 3, 3) float64."""
    rng = np.random.default_rng(seed)
    lib = MeshLibrary(cube_meshes())
    graph = lib.pack(lib.shape_ids(["cube"] * num_graphs), torch.from_numpy(rng.uniform(0.7, 1.4, num_graphs)),
                     torch.full((num_graphs,), 0.4), torch.full((num_graphs,), 0.3))
    pos = torch.from_numpy(rng.uniform([-2, -2, 0.2], [2, 2, 1.0], (num_graphs, 1, 3)))
    pos = pos + torch.arange(3, dtype=DTYPE)[None, :, None] * torch.from_numpy(rng.normal(0, 0.1, (num_graphs, 1, 3)))
    rot = random_rotations(num_graphs * 3, seed).reshape(num_graphs, 3, 3, 3)
    return graph, vertices_from_poses(graph, pos, rot)


def small_simulator(spec=SPEC, **features):
    torch.manual_seed(0)
    sim = LearnedSimulator(ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, processor_repeats=1),
                           FeatureConfig(**features), spec)
    # Give the normalisers statistics from a few batches, as the first training steps would.
    sim.train()
    for seed in range(3):
        graph, hist = cube_batch(seed=seed)
        sim.loss(hist, hist[:, -1] + 0.01, graph)
    return sim.eval()


def test_integrator_and_inverse_round_trip():
    x = torch.from_numpy(np.random.default_rng(0).normal(size=(3, 50, 3)) * 100)
    a = acceleration_of(x[0], x[1], x[2])
    assert torch.allclose(integrate(x[0], x[1], a), x[2], rtol=0, atol=1e-12)
    acc = torch.from_numpy(np.random.default_rng(1).normal(size=(50, 3)))
    assert torch.allclose(acceleration_of(x[0], x[1], integrate(x[0], x[1], acc)), acc, rtol=0, atol=1e-12)
    # Constant acceleration from rest: x_t = a t^2 / 2 satisfies the update exactly up to round-off.
    t = torch.arange(3, dtype=DTYPE)[:, None, None]
    g = torch.tensor([0.0, 0.0, -10 / 144], dtype=DTYPE)
    traj = 0.5 * g * t * t
    assert torch.allclose(acceleration_of(traj[0], traj[1], traj[2]), g.expand(1, 3))


def test_normalizer_statistics_round_trip_and_freeze():
    data = torch.from_numpy(np.random.default_rng(0).normal([1.0, -3.0], [2.0, 0.5], (4000, 2))).float()
    norm = Normalizer(2, max_accumulations=2)
    norm(data[:2000], accumulate=True)
    norm(data[2000:], accumulate=True)
    norm(data * 100, accumulate=True)  # over budget: ignored
    assert torch.allclose(norm.mean, data.double().mean(0), atol=1e-6)
    assert torch.allclose(norm.std, data.double().std(0, unbiased=False), atol=1e-6)
    assert torch.allclose(norm.inverse(norm(data)), data, atol=1e-5)
    fresh = Normalizer(2, max_accumulations=2)
    fresh.load_state_dict(norm.state_dict())
    assert torch.equal(fresh(data), norm(data))


def test_normalizer_std_floor_for_constant_features():
    norm = Normalizer(1, 10)
    norm(torch.full((10, 1), 3.0), accumulate=True)
    assert float(norm.std) == pytest.approx(1e-5)
    assert torch.equal(norm(torch.full((2, 1), 3.0)), torch.zeros(2, 1))


def test_simulator_state_dict_holds_normalisers():
    sim = small_simulator()
    keys = sim.state_dict().keys()
    assert "target_normalizer.sum" in keys and "node_normalizers.velocity.count" in keys
    assert "edge_normalizers.relative.sum_squared" in keys
    assert float(sim.state_dict()["target_normalizer.count"]) > 0


def test_eval_mode_does_not_accumulate():
    sim = small_simulator()
    before = {k: v.clone() for k, v in sim.state_dict().items()}
    graph, hist = cube_batch(seed=7)
    sim.loss(hist, hist[:, -1], graph)
    assert all(torch.equal(before[k], v) for k, v in sim.state_dict().items())


@pytest.mark.parametrize("floor, shift", [(True, [1e3, -1e3, 0.0]), (False, [1e3, -1e3, 1e3])])
def test_relative_encoding_is_translation_equivariant(floor, shift):
    sim = small_simulator(spec=ModelSpec(floor=Floor(0.0) if floor else None, materials_vary=False))
    graph, hist = cube_batch(seed=3)
    moved = hist + torch.tensor(shift, dtype=DTYPE)
    with torch.no_grad():
        a = sim.predict_acceleration(hist, graph)
        b = sim.predict_acceleration(moved, graph)
    assert torch.allclose(a, b, rtol=0, atol=1e-5 * float(a.abs().max()))
    with torch.no_grad():
        x_next = sim.predict_next(*hist.unbind(1), graph)
        x_next_moved = sim.predict_next(*moved.unbind(1), graph)
    assert torch.allclose(x_next_moved - torch.tensor(shift, dtype=DTYPE), x_next, atol=1e-9)


def test_absolute_encoding_is_not_translation_equivariant():
    sim = small_simulator(encoding="absolute")
    graph, hist = cube_batch(seed=3)
    with torch.no_grad():
        a = sim.predict_acceleration(hist, graph)
        b = sim.predict_acceleration(hist + torch.tensor([3.0, 0.0, 0.0], dtype=DTYPE), graph)
    assert not torch.allclose(a, b, atol=1e-3)
    assert [n for n, _ in sim.layout.node_groups] == ["velocity", "floor", "rest_position", "position"]
    assert sim.layout.edge_groups == ()


def test_floor_feature_is_clipped_distance():
    sim = small_simulator(floor_clip=0.5)
    graph, hist = cube_batch(seed=0)
    hist[:, :, 2] = torch.linspace(-1.0, 2.0, graph.num_nodes, dtype=DTYPE)[:, None]
    floor = raw_node_features(sim.layout, hist, graph)["floor"][:, 0]
    assert torch.allclose(floor, hist[:, -1, 2].clamp(0, 0.5).float())


def test_feature_switches_change_input_widths():
    full = small_simulator()
    lean = small_simulator(rest_position=False, rest_edges=False, floor_distance=False)
    assert full.layout.node_size == 6 + 1 + 3 and full.layout.edge_size == 8
    assert lean.layout.node_size == 6 and lean.layout.edge_size == 4
    graph, hist = cube_batch()
    assert lean.predict_acceleration(hist, graph).shape == (graph.num_nodes, 3)


# ---- shape matching ---------------------------------------------------------------------

def rigid_setup(batch=4, seed=0):
    rng = np.random.default_rng(seed)
    rest = torch.from_numpy(rng.normal(size=(batch, 10, 3)))
    rot = random_rotations(batch, seed)
    t = torch.from_numpy(rng.normal(size=(batch, 3)) * 5)
    return rest, rot, t, rest @ rot.transpose(1, 2) + t[:, None]


def test_shape_match_recovers_rotation_and_translation():
    rest, rot, t, x = rigid_setup()
    r_est, t_est, proj = shape_match(x, rest)
    assert torch.allclose(r_est, rot, atol=1e-12) and torch.allclose(t_est, t, atol=1e-12)
    assert torch.allclose(proj, x, atol=1e-12)


def test_shape_match_from_noisy_points_is_rigid_and_close():
    rest, rot, t, x = rigid_setup(seed=1)
    noisy = x + 1e-3 * torch.from_numpy(np.random.default_rng(2).normal(size=x.shape))
    r_est, t_est, proj = shape_match(noisy, rest)
    assert torch.allclose(r_est, rot, atol=3e-3) and torch.allclose(t_est, t, atol=3e-3)
    # The projection is a rigid copy of the rest mesh: every pairwise distance preserved.
    assert torch.allclose(torch.cdist(proj, proj), torch.cdist(rest, rest), atol=1e-10)


def test_shape_match_never_returns_a_reflection():
    rest, rot, t, x = rigid_setup(seed=3)
    mirrored = x * torch.tensor([-1.0, 1.0, 1.0], dtype=DTYPE)
    r_est, _, proj = shape_match(mirrored, rest)
    assert torch.allclose(torch.linalg.det(r_est), torch.ones(len(rest), dtype=DTYPE), atol=1e-12)
    assert torch.allclose(r_est @ r_est.transpose(1, 2), torch.eye(3, dtype=DTYPE).expand_as(r_est), atol=1e-12)
    assert torch.allclose(torch.cdist(proj, proj), torch.cdist(rest, rest), atol=1e-10)


def test_shape_match_accepts_float32():
    rest, _, _, x = rigid_setup(seed=4)
    r_est, t_est, proj = shape_match(x.float(), rest.float())
    assert r_est.dtype == torch.float32 and torch.allclose(proj.double(), x, atol=1e-4)


def test_packed_shape_match_equals_dense_per_graph():
    rest, rot, t, x = rigid_setup(seed=5)
    noisy = x + 0.05 * torch.from_numpy(np.random.default_rng(6).normal(size=x.shape))
    node_graph = torch.arange(4).repeat_interleave(10)
    r_p, t_p, proj_p = shape_match_packed(noisy.reshape(-1, 3), rest.reshape(-1, 3), node_graph, 4)
    r_d, t_d, proj_d = shape_match(noisy, rest)
    assert torch.allclose(r_p, r_d, atol=1e-12) and torch.allclose(t_p, t_d, atol=1e-12)
    assert torch.allclose(proj_p, proj_d.reshape(-1, 3), atol=1e-12)


def test_rollout_with_shape_matching_keeps_meshes_rigid():
    sim = small_simulator()
    graph, hist = cube_batch(seed=2)
    traj = sim.rollout(hist, graph, steps=4)
    assert traj.shape == (4, graph.num_nodes, 3) and traj.dtype == DTYPE
    for x in traj:
        for g in range(graph.num_graphs):
            pts, rest = x[graph.node_graph == g], graph.rest[graph.node_graph == g]
            assert torch.allclose(torch.cdist(pts, pts), torch.cdist(rest, rest), atol=1e-9)


def test_shape_match_of_a_diverged_graph_spoils_only_that_graph():
    rest, rot, t, x = rigid_setup(seed=7)
    x[1, 3] = torch.nan
    x[2, 0, 0] = torch.inf
    node_graph = torch.arange(4).repeat_interleave(10)
    r_p, t_p, proj = shape_match_packed(x.reshape(-1, 3), rest.reshape(-1, 3), node_graph, 4)
    assert torch.isnan(r_p[1]).all() and torch.isnan(r_p[2]).all()
    assert torch.allclose(r_p[[0, 3]], rot[[0, 3]], atol=1e-12)
    assert torch.isfinite(proj[node_graph == 0]).all() and torch.isnan(proj[node_graph == 1]).all()


def z_turns(angle: torch.Tensor) -> torch.Tensor:
    """(N,) angles -> (N, 3, 3) rotations about z by them."""
    c, s = torch.cos(angle), torch.sin(angle)
    turn = torch.zeros(angle.shape[0], 3, 3, dtype=angle.dtype, device=angle.device)
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1], turn[:, 2, 2] = c, -s, s, c, 1.0
    return turn


def test_per_node_turns_equal_the_matrix_products():
    """The rollout's cheap forms against the plain matrix products they replace:
    each node turned by its graph's rotation, turns about z from cosines and sines, and the
    floor's diagonal maps of the body-frame symmetries."""
    from gns.symmetry import mapped_symmetries
    from gns.geometry import rotate_nodes
    from gns.symmetry import turn_about_z
    rot = random_rotations(4, seed=1)
    node_graph = torch.tensor([0, 0, 1, 2, 2, 2, 3])
    v = torch.from_numpy(np.random.default_rng(2).normal(size=(7, 3)))
    assert torch.allclose(rotate_nodes(rot, node_graph, v), (rot[node_graph] @ v[:, :, None])[..., 0], atol=1e-14)
    angle = torch.from_numpy(np.random.default_rng(3).uniform(-np.pi, np.pi, 7))
    history = torch.from_numpy(np.random.default_rng(4).normal(size=(7, 3, 3)))
    expected = torch.einsum("nij,ntj->nti", z_turns(angle), history)
    assert torch.allclose(turn_about_z(history, torch.cos(angle), torch.sin(angle)), expected, atol=1e-14)
    assert torch.allclose(turn_about_z(expected, torch.cos(angle), -torch.sin(angle)), history, atol=1e-14)
    graph, _ = cube_batch(num_graphs=2)
    for g in (torch.diag(torch.tensor([-1.0, 1.0, 1.0])), torch.diag(torch.tensor([-1.0, -1.0, 1.0])), z_turns(
            torch.tensor([0.3]))[0]):
        g = g.to(DTYPE)
        assert torch.allclose(mapped_symmetries(graph, g), g @ graph.symmetries @ g.T, atol=1e-14)
