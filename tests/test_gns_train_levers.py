"""Contact-weighted window sampling and pushforward (unrolled) training."""
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from gns_fixtures import FRAME_RATE, GRAVITY, cube_meshes, toss_scene, write_toss_dataset

from datagen.shards import Dataset, Scene
from gns.config import ConfigError, build_config
from gns.data import ObjectTracks
from gns.graph import MeshLibrary
from gns.geometry import shape_match_packed
from gns.checkpoint import build_simulator, read_checkpoint
from gns.train import unrolled_loss
from gns.train import train
from test_gns_train import TINY, metrics, quiet, tiny

G_STEP = torch.tensor(GRAVITY, dtype=torch.float64) / FRAME_RATE ** 2


def scene(positions: np.ndarray) -> Scene:
    """One unit cube along given centre positions (T, 3), not rotating."""
    t = len(positions)
    quats = np.tile([1.0, 0, 0, 0], (t, 1))
    return Scene(positions=positions[:, None], quaternions=quats[:, None], velocities=np.zeros((t, 1, 3)),
                 angular_velocities=np.zeros((t, 1, 3)), shape=["cube"], material=["metal"], scale=np.ones(1),
                 mass=np.ones(1), friction=np.array([0.4]), restitution=np.array([0.3]))


def ballistic(frames: int, z0: float = 50.0) -> np.ndarray:
    t = np.arange(frames) / FRAME_RATE
    return np.stack([0.5 * t, 0 * t, z0 + 2 * t + 0.5 * GRAVITY[2] * t ** 2], axis=1)


def test_free_flight_is_never_contact_and_rest_always_is():
    lib = MeshLibrary(cube_meshes())
    rest = np.tile([0.0, 0.0, 0.5], (10, 1))
    tracks = ObjectTracks([scene(ballistic(10)), scene(rest)], lib)
    tracks.mark_contacts(G_STEP, 0.5)
    flying = tracks.window_scene == 0
    assert not tracks.contact[flying].any()
    assert tracks.contact[~flying].all()


def test_a_bounce_flags_exactly_the_windows_whose_targets_hold_it():
    # free fall, then at frame 6 the vertical velocity is reversed (halved) and free fall goes on:
    # only the second difference at frame 6 departs from gravity
    x = ballistic(12)
    bounce = 6
    dt = 1.0 / FRAME_RATE
    v = (x[bounce] - x[bounce - 1]) / dt + 0.5 * np.array(GRAVITY) * dt   # velocity at the bounce frame
    v[2] = -0.5 * v[2]
    k = np.arange(1, 12 - bounce)[:, None] * dt
    x[bounce + 1:] = x[bounce] + v * k + 0.5 * np.array(GRAVITY) * k ** 2
    tracks = ObjectTracks([scene(x)], MeshLibrary(cube_meshes()), unroll=1)
    tracks.mark_contacts(G_STEP, 0.5)
    # window f predicts frame f+3 from f..f+2; its acceleration is taken at frame f+2
    flagged = [int(f) for f in tracks.window_first[tracks.contact]]
    assert flagged == [bounce - 2]
    unrolled = ObjectTracks([scene(x)], MeshLibrary(cube_meshes()), unroll=3)
    unrolled.mark_contacts(G_STEP, 0.5)
    # with 3 targets (frames f+3..f+5) the accelerations at f+2..f+4 count
    assert [int(f) for f in unrolled.window_first[unrolled.contact]] == [bounce - 4, bounce - 3, bounce - 2]


def test_contact_fraction_one_draws_only_contact_windows():
    lib = MeshLibrary(cube_meshes())
    tracks = ObjectTracks([scene(ballistic(10)), scene(np.tile([0.0, 0.0, 0.5], (10, 1)))], lib)
    tracks.mark_contacts(G_STEP, 0.5)
    rng = np.random.default_rng(0)
    for _ in range(5):
        batch = tracks.sample(rng, 6, False, 0.0, contact_fraction=1.0)
        # every graph of the batch is the resting cube: its centre never moves
        assert torch.allclose(batch.history[:, 0], batch.target)
    resting = []
    for _ in range(100):
        b = tracks.sample(rng, 8, False, 0.0, contact_fraction=0.5)
        still = (b.history[:, 0] - b.target).norm(dim=-1).reshape(8, 8).amax(dim=1) < 1e-12  # per graph
        resting += still.tolist()
    # half drawn from contact windows (all resting), half from all windows (half resting): 3/4
    assert abs(np.mean(resting) - 0.75) < 0.06


def test_unrolled_windows_carry_the_true_future(tmp_path):
    ds = Dataset(write_toss_dataset(tmp_path, train=3, valid=0, frames=10))
    lib = MeshLibrary(ds.meshes)
    one, three = (ObjectTracks(ds.load("train"), lib, unroll=u) for u in (1, 3))
    assert three.num_windows == one.num_windows - 3 * 2
    w = torch.tensor([0, 4])
    b3 = three.batch(w)
    for k in range(3):  # target k of a window is the one-step target of the window k frames later
        later = one.batch(torch.tensor([int(three.window_first[0]) + k, 4 + k]))
        assert torch.allclose(b3.targets[:, k], later.target)


@pytest.mark.parametrize("features", [(), ("features.lowest_vertices=3", "features.highest_vertices=1",
                                             "features.centre_node=true")])
@pytest.mark.parametrize("rigid", [0.0, 1.0])
def test_unrolled_loss_is_the_mean_of_one_step_losses_on_its_own_predictions(tmp_path, features, rigid):
    """Step 2 starts from predict_next's positions (shape-matched, detached): unrolled_loss takes
    them from step 1's own forward pass, also where the network sees only some of the nodes."""
    ds = Dataset(write_toss_dataset(tmp_path, train=3, valid=0, frames=10))
    from gns.data import feature_spec
    scenes = ds.load("train")
    cfg = build_config(path=TINY, overrides=list(features))
    sim = build_simulator(cfg, feature_spec(ds, scenes)).eval()   # eval: normalisers frozen
    lib = sim.mesh_library(ds.meshes)
    tracks = ObjectTracks(scenes, lib, unroll=2)
    batch = tracks.batch(torch.tensor([0, 5]))
    g = batch.graph
    first = sim.loss(batch.history, batch.target, g, rigid)
    with torch.no_grad():
        x = shape_match_packed(sim.predict_next(*batch.history.unbind(1), g), g.rest, g.node_graph, g.num_graphs)[2]
    second = sim.loss(torch.stack([batch.history[:, 1], batch.history[:, 2], x], 1), batch.future[:, 0], g, rigid)
    unrolled = unrolled_loss(sim, batch, rigid)
    assert torch.allclose(unrolled, (first + second) / 2, rtol=1e-6, atol=0)
    assert not torch.allclose(first, second, rtol=1e-3)     # the two steps differ: the second one counts
    one = ObjectTracks(scenes, lib).batch(torch.tensor([0, 5]))
    assert torch.allclose(unrolled_loss(sim, one, rigid), sim.loss(one.history, one.target, one.graph, rigid))


def test_training_with_both_levers_resumes_exactly(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=4, valid=1, frames=10)
    over = ("train.steps=12", "train.checkpoint_every=6", "train.unroll_steps=2", "train.contact_fraction=0.5",
            "valid.every=6")
    train(data, tmp_path / "a", tiny(*over), log=quiet)
    train(data, tmp_path / "b", tiny(*over[1:], "train.steps=6"), log=quiet)
    train(data, tmp_path / "b", tiny(*over), resume=True, log=quiet)
    a, b = read_checkpoint(tmp_path / "a" / "latest.pt"), read_checkpoint(tmp_path / "b" / "latest.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert metrics(tmp_path / "a")[-1]["loss"] == metrics(tmp_path / "b")[-1]["loss"]


@pytest.mark.parametrize("key", ["train.unroll_steps=0", "train.contact_fraction=1.5", "train.contact_threshold=0",
                                 "train.scenes=-1"])
def test_bad_lever_values_are_one_line_errors(key):
    with pytest.raises(ConfigError, match=key.split("=")[0]):
        build_config(path=TINY, overrides=[key])


def sim_and_batch(tmp_path, *overrides):
    ds = Dataset(write_toss_dataset(tmp_path, train=3, valid=0, frames=10))
    from gns.data import feature_spec
    scenes = ds.load("train")
    sim = build_simulator(build_config(path=TINY, overrides=list(overrides)), feature_spec(ds, scenes)).eval()
    return sim, ObjectTracks(scenes, MeshLibrary(ds.meshes)).batch(torch.tensor([0, 3, 6]))


def test_symmetrized_predictions_are_exactly_mirror_and_half_turn_equivariant(tmp_path):
    sim, b = sim_and_batch(tmp_path)
    from dataclasses import replace
    sim.options = sim.options.replace(symmetrize=True)
    a = sim.predict_acceleration(b.history, b.graph)
    scale = float(a.abs().max())   # an untrained network's answers are small: compare relative to them
    for m in ((-1.0, 1.0, 1.0), (1.0, -1.0, 1.0), (-1.0, -1.0, 1.0)):
        g = torch.tensor(m, dtype=torch.float64)
        mapped = sim.predict_acceleration(b.history * g, replace(b.graph, rest=b.graph.rest * g))
        assert float((mapped - a * g).abs().max()) < 1e-6 * scale, m
    sim.options = sim.options.replace(symmetrize=False)   # the network alone is not exactly equivariant (control)
    plain = sim.predict_acceleration(b.history, b.graph)
    g = torch.tensor((-1.0, 1.0, 1.0), dtype=torch.float64)
    mirrored = sim.predict_acceleration(b.history * g, replace(b.graph, rest=b.graph.rest * g))
    assert float((mirrored - plain * g).abs().max()) > 1e-3 * float(plain.abs().max())


def test_d4_symmetrized_predictions_are_exactly_quarter_turn_equivariant(tmp_path):
    sim, b = sim_and_batch(tmp_path)
    from dataclasses import replace

    from gns.symmetry import symmetry_group
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    diagonal = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def off(g):
        """How far the prediction for the mapped scene is from the mapped prediction, relative."""
        a = sim.predict_acceleration(b.history, b.graph)
        m = sim.predict_acceleration(b.history @ g.T, replace(b.graph, rest=b.graph.rest @ g.T))
        return float((m - a @ g.T).abs().max() / a.abs().max())
    sim.options = sim.options.replace(symmetrize="d4")
    assert off(quarter) < 1e-6 and off(diagonal) < 1e-6
    sim.options = sim.options.replace(symmetrize="d2")    # the mirrors alone do not hold a quarter turn (control)
    assert off(quarter) > 1e-3
    assert symmetry_group(True) == "d2" and symmetry_group(False) is None
    with pytest.raises(ValueError, match="unknown symmetry group 'd6'"):
        symmetry_group("d6")


def test_the_two_and_four_image_groups_hold_exactly_their_own_maps_and_not_the_others(tmp_path):
    sim, b = sim_and_batch(tmp_path)
    from dataclasses import replace
    mirror_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    half = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def off(g):
        a = sim.predict_acceleration(b.history, b.graph)
        m = sim.predict_acceleration(b.history @ g.T, replace(b.graph, rest=b.graph.rest @ g.T))
        return float((m - a @ g.T).abs().max() / a.abs().max())
    for group, holds, fails in (("d1", mirror_x, half), ("c2", half, mirror_x), ("c4", quarter, mirror_x)):
        sim.options = sim.options.replace(symmetrize=group)
        assert off(holds) < 1e-6, group
        assert off(fails) > 1e-3, group   # an untrained network is far from the map the group lacks
    sim.options = sim.options.replace(symmetrize="c4")
    assert off(half) < 1e-6   # the half turn is two quarter turns


def test_a_canonical_heading_makes_the_model_exactly_equivariant_to_any_turn_about_z(tmp_path):
    def turned_off(sim, b, angle):
        """How far the prediction for the scene turned about z (and moved) is from the turned
        prediction, relative to the prediction."""
        c, s = math.cos(angle), math.sin(angle)
        q = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        shift = torch.tensor([0.7, -1.3, 0.0], dtype=torch.float64)
        a = sim.predict_acceleration(b.history, b.graph)
        m = sim.predict_acceleration(b.history @ q.T + shift, b.graph)
        return float((m - a @ q.T).abs().max() / a.abs().max())
    sim, b = sim_and_batch(tmp_path, "features.canonical_heading=true")
    assert sim.canonical_heading
    for angle in (0.3, 2.0, -2.9):
        assert turned_off(sim, b, angle) < 1e-5, angle   # float32 network: the same inputs to rounding
    plain, b = sim_and_batch(tmp_path / "plain")           # control: the network alone is not
    assert turned_off(plain, b, 2.0) > 1e-3
    # at rest (no horizontal velocity) the heading is the world's: the model runs as it reads
    still = b.history[:, -1:].expand(-1, 3, -1).clone()
    sim.canonical_heading = False
    ref = sim(still, b.graph)
    sim.canonical_heading = True
    assert torch.allclose(sim(still, b.graph), ref, atol=1e-6)


def test_an_ensemble_averages_its_members_predictions_and_refuses_a_member_reading_other_graphs(tmp_path):
    sim, b = sim_and_batch(tmp_path)
    other, _ = sim_and_batch(tmp_path / "other")   # a second build draws other initial weights
    a, o = sim.predict_acceleration(b.history, b.graph), other.predict_acceleration(b.history, b.graph)
    assert not torch.allclose(a, o, atol=1e-6)
    sim.set_ensemble([other])
    torch.testing.assert_close(sim.predict_acceleration(b.history, b.graph), (a + o) / 2, rtol=0, atol=1e-9)
    sim.options = sim.options.replace(symmetrize=True)    # each member symmetrized as the model is asked to be: still exactly equivariant
    both = sim.predict_acceleration(b.history, b.graph)
    g = torch.tensor((-1.0, 1.0, 1.0), dtype=torch.float64)
    mirrored = sim.predict_acceleration(b.history * g, replace(b.graph, rest=b.graph.rest * g))
    assert float((mirrored - both * g).abs().max()) < 1e-6 * float(both.abs().max())
    centred, _ = sim_and_batch(tmp_path / "centred", "features.centre_node=true")
    with pytest.raises(ValueError, match="member 1 differs .* network mesh"):
        sim.set_ensemble([centred])
    # other node features over the same graphs (the floor seen from farther): each member
    # computes its own, and free flight waits until the farthest-seeing member's floor is clear
    far, _ = sim_and_batch(tmp_path / "far", "features.floor_clip=1.5", "features.floor_signed=true")
    f = far.predict_acceleration(b.history, b.graph)
    sim.options = sim.options.replace(symmetrize=False)
    assert sim.free_flight_clip == sim.layout.floor_clip == 0.5
    sim.set_ensemble([far])
    torch.testing.assert_close(sim.predict_acceleration(b.history, b.graph), (a + f) / 2, rtol=0, atol=1e-9)
    assert sim.free_flight_clip == 1.5
    for key, value in (("floor_z", 0.25), ("collision_radius", 0.1)):   # what the graphs or free flight hang on
        far.layout = replace(far.layout, **{key: value})
        with pytest.raises(ValueError, match="member 1 differs .* (floor|collision)"):
            sim.set_ensemble([far])
        far.layout = replace(far.layout, **{key: getattr(sim.layout, key)})


def test_an_ensemble_member_on_spokes_only_reads_its_own_mesh_edges(tmp_path):
    # a full-mesh and a spokes-only model (both with centre nodes) share nodes, not mesh edges:
    # each member reads the step's graph with its own edges, rebuilt from the faces
    from gns.data import feature_spec
    ds = Dataset(write_toss_dataset(tmp_path, train=3, valid=0, frames=10))
    scenes = ds.load("train")
    spec = feature_spec(ds, scenes)

    def built(*overrides):
        cfg = build_config(path=TINY, overrides=["features.centre_node=true", *overrides])
        sim = build_simulator(cfg, spec).eval()
        return sim, ObjectTracks(scenes, sim.mesh_library(ds.meshes)).batch(torch.tensor([0, 3, 6]))

    (full, bf), (spokes, bs) = built(), built("features.surface_edges=false")
    assert bs.graph.mesh_edges.senders.numel() < bf.graph.mesh_edges.senders.numel()
    a = full.predict_acceleration(bf.history, bf.graph)
    o = spokes.predict_acceleration(bs.history, bs.graph)
    full.set_ensemble([spokes])
    torch.testing.assert_close(full.predict_acceleration(bf.history, bf.graph), (a + o) / 2, rtol=0, atol=1e-9)
    spokes.set_ensemble([built()[0]])   # the other way round: a full-mesh member of a spokes model
    full.set_ensemble([])
    a = spokes.members[0].predict_acceleration(bf.history, bf.graph)
    torch.testing.assert_close(spokes.predict_acceleration(bs.history, bs.graph), (a + o) / 2, rtol=0, atol=1e-9)


def test_upsampling_a_strided_rollout_recovers_a_smooth_trajectory_at_every_frame():
    from gns.geometry import quat_from_axis_angle
    from gns.metrics import rotation_error_deg
    from gns.at_data_rate import upsample_scene
    t = np.arange(21) / FRAME_RATE
    x = ballistic(21)
    q = quat_from_axis_angle(np.array([0.3, 0.2, 1.0]), 2.0 * t)    # constant spin
    full = scene(x)
    full = Scene(full.positions, q[:, None], full.velocities, full.angular_velocities, full.shape, full.material,
                 full.scale, full.mass, full.friction, full.restitution)
    coarse = full.every(4)                                               # frames 0, 4, .., 20
    up, truth = upsample_scene(coarse, 4, full, FRAME_RATE)
    assert up.num_frames == truth.num_frames == 21
    assert np.allclose(up.positions[::4], coarse.positions)
    assert np.allclose(up.positions, truth.positions, atol=1e-9)        # a cubic spline is exact on a parabola
    assert rotation_error_deg(up.quaternions[:, 0], truth.quaternions[:, 0]).max() < 1e-6   # slerp is exact here
    # a rollout shorter than the truth is scored only where it reaches
    up, truth = upsample_scene(full.every(4), 4, scene(ballistic(23)), FRAME_RATE)
    assert truth.num_frames == up.num_frames == 21


def test_all_phases_gives_a_strided_model_every_window_of_the_data(tmp_path):
    from gns.data import load_data
    data = write_toss_dataset(tmp_path, train=3, valid=1, frames=12)
    _, plain, _ = load_data(data, tiny("features.frame_stride=2"))
    _, phased, valid = load_data(data, tiny("features.frame_stride=2", "train.all_phases=true"))
    # a window at stride k spans 3k + 1 recorded frames: 12 - 6 = 6 start frames per scene
    assert phased.num_windows == 3 * (12 - 3 * 2)
    assert plain.num_windows == 3 * (6 - 3)          # from frame 0 only: frames 0, 2, .., 10
    assert valid.num_windows == 1 * (6 - 3)          # validation stays at phase 0
    # phase 1 of a scene is its odd frames
    ds = Dataset(data)
    sc = ds.load("train")[0]
    assert np.array_equal(phased.positions[6:12].numpy(), sc.positions[1::2, 0])


def test_train_scenes_trains_on_the_first_scenes_exactly_as_a_dataset_of_that_many(tmp_path):
    from gns.data import load_data
    large = write_toss_dataset(tmp_path / "large", train=6, valid=1, frames=10)
    small = write_toss_dataset(tmp_path / "small", train=3, valid=1, frames=10)
    spec_part, part, _ = load_data(large, tiny("train.scenes=3"))
    spec_small, whole, _ = load_data(small, tiny())
    assert part.num_scenes == whole.num_scenes == 3 and part.num_windows == whole.num_windows
    assert torch.equal(part.positions, whole.positions)
    assert spec_part.ranges == spec_small.ranges          # the ranges kept with the model are the subset's
    _, every, _ = load_data(large, tiny("train.scenes=0"))
    assert every.num_scenes == 6
    with pytest.raises(ConfigError, match="train.scenes=7, but .* holds 6 train scenes"):
        load_data(large, tiny("train.scenes=7"))

