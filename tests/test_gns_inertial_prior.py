"""The inertial prior the network's acceleration is added to (model.inertial_prior): the paper's
straight-line extrapolation per vertex, or each object turning on rigidly
(gns.simulator.rigid_extrapolation). Physics first: a spinning body with no force on it must
keep its spin. And the loss of what a rollout keeps of a step (train.rigid_loss): the
shape-matched prediction against the shape-matched truth."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from datagen.cli import main as datagen_main
from datagen.shards import Dataset
from gns.config import ConfigError, build_config
from gns.data import ObjectTracks, feature_spec
from gns.graph import MeshLibrary
from gns.rigid import integrate, rigid_extrapolation, shape_match_packed
from gns.simulator import LearnedSimulator
from gns.stability import resting_scene
from gns.train import CheckpointError, read_checkpoint, train
from gns_fixtures import write_toss_dataset
from test_gns_train import quiet, tiny

import gns

SPIN = np.radians([9.0, -14.0, 18.0])   # world angular velocity, radians a frame: 24.7 degrees a frame


def _spinning(rest: torch.Tensor, start: np.ndarray, step: np.ndarray, k: int) -> torch.Tensor:
    rot = torch.tensor(Rotation.from_rotvec(SPIN * k).as_matrix())
    return rest @ rot.T + torch.tensor(start + step * k)


def _two_objects():
    """A cube (8 vertices) and an irregular body (11), centred on their vertex means."""
    gen = torch.Generator().manual_seed(0)
    cube = torch.tensor([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)], dtype=torch.float64)
    lump = torch.rand(11, 3, generator=gen, dtype=torch.float64) - 0.5
    lump = lump - lump.mean(0)
    node_graph = torch.cat([torch.zeros(8, dtype=torch.long), torch.ones(11, dtype=torch.long)])
    return cube, lump, node_graph


def test_rigid_extrapolation_turns_spinning_objects_on_exactly_where_straight_lines_lose_spin():
    cube, lump, node_graph = _two_objects()
    frames = [torch.cat([_spinning(cube, np.array([0.0, 0.0, 3.0]), np.array([0.2, 0.0, 0.1]), k),
                         _spinning(lump, np.array([5.0, 1.0, 2.0]), np.array([-0.1, 0.3, 0.0]), k)]) for k in range(3)]
    rigid = rigid_extrapolation(frames[0], frames[1], node_graph, 2)
    torch.testing.assert_close(rigid, frames[2], rtol=0, atol=1e-12)
    # the straight-line update, shape-matched, turns by less than the body turned in the last frame
    rest = torch.cat([cube, lump])
    linear = integrate(frames[0], frames[1], torch.zeros_like(frames[1]))
    rot, _, _ = shape_match_packed(linear, rest, node_graph, 2)
    turned = Rotation.from_matrix(rot.numpy()).magnitude()
    expected = 2 * np.linalg.norm(SPIN)
    assert np.all(turned < 0.95 * expected), (np.degrees(turned), math.degrees(expected))


def test_rigid_extrapolation_commutes_with_rotations_and_translations():
    cube, lump, node_graph = _two_objects()
    gen = torch.Generator().manual_seed(1)
    x0 = torch.cat([cube, lump]) + 0.01 * torch.randn(19, 3, generator=gen, dtype=torch.float64)
    # not rigid on purpose (noisy vertices, as training inputs are): equivariance must hold anyway
    x1 = x0 @ torch.tensor(Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()).T \
        + 0.02 * torch.randn(19, 3, generator=gen, dtype=torch.float64)
    q = torch.tensor(Rotation.from_rotvec([0.7, -1.1, 0.4]).as_matrix())
    shift = torch.tensor([3.0, -2.0, 10.0], dtype=torch.float64)
    moved = rigid_extrapolation(x0 @ q.T + shift, x1 @ q.T + shift, node_graph, 2)
    torch.testing.assert_close(moved, rigid_extrapolation(x0, x1, node_graph, 2) @ q.T + shift, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def movi(tmp_path_factory):
    out = tmp_path_factory.mktemp("prior") / "data"
    assert datagen_main(["toss", "--out", str(out), "--scenes", "0", "--test", "2", "--seed", "3",
                         "--shapes", "beveled_cube,cylinder,sphere", "--quiet"]) == 0
    ds = Dataset(out)
    return ds, ds.load("test")


def _force_free(ds, scenes, prior: str) -> LearnedSimulator:
    """A simulator whose network predicts zero acceleration everywhere (decoder zeroed)."""
    cfg = build_config(path="configs/gns_tiny.toml", overrides=[f"model.inertial_prior={prior}"])
    sim = LearnedSimulator(cfg.model, cfg.features, feature_spec(ds, scenes)).eval()
    with torch.no_grad():
        sim.network.decoder[-1].weight.zero_()
        sim.network.decoder[-1].bias.zero_()
        sim.target_normalizer.count.fill_(1.0)
        sim.target_normalizer.sum_squared.fill_(1.0)
    return sim


def _spin_window(ds):
    """A beveled cube far above the floor spinning at SPIN: graph and vertices (N, 4, 3)."""
    sc = resting_scene("beveled_cube", 1.4, ds.meshes, floor_z=0.0)
    sc.positions[:, 0, 2] = 1e3
    quat = Rotation.from_rotvec(np.outer(np.arange(sc.num_frames), SPIN)).as_quat()   # x y z w
    sc.quaternions[:, 0] = quat[:, [3, 0, 1, 2]]
    graph, verts, _ = ObjectTracks([sc], MeshLibrary(ds.meshes)).track_vertices(torch.arange(1), 4)
    return graph, verts


def test_the_rigid_loss_scores_only_what_shape_matching_keeps(movi):
    ds, scenes = movi
    sim = _force_free(ds, scenes, "rigid").eval()   # zero acceleration: the prior is the prediction
    graph, verts = _spin_window(ds)
    history, truth = verts[:, :3], verts[:, 3]
    # the force-free spin is predicted exactly: nothing to learn
    assert float(sim.loss(history, truth, graph, rigid=1.0)) < 1e-16
    # a target swollen about its centre is a non-rigid change that shape matching takes away:
    # the per-node loss sees it, the rigid term does not
    centre = truth.mean(0)
    swollen = centre + 1.01 * (truth - centre)
    plain = float(sim.loss(history, swollen, graph))
    assert plain > 1e-8
    assert float(sim.loss(history, swollen, graph, rigid=1.0)) == pytest.approx(plain, rel=1e-6)
    # a shifted target is a rigid change: both terms see all of it
    shifted = truth + torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64)
    plain = float(sim.loss(history, shifted, graph))
    assert float(sim.loss(history, shifted, graph, rigid=1.0)) == pytest.approx(2 * plain, rel=1e-6)
    # under the straight-line prior, the zero answer loses spin: the rigid term sees the under-turn
    linear = _force_free(ds, scenes, "linear").eval()
    assert float(linear.loss(history, truth, graph, rigid=1.0)) > float(linear.loss(history, truth, graph)) > 0


def test_the_rigid_loss_has_a_finite_gradient_and_trains(tmp_path, movi):
    ds, scenes = movi
    sim = _force_free(ds, scenes, "linear")
    torch.nn.init.normal_(sim.network.decoder[-1].weight, std=0.1)
    graph, verts = _spin_window(ds)
    sim.eval()
    sim.loss(verts[:, :3], verts[:, 3], graph, rigid=2.0).backward()
    grads = [p.grad for p in sim.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads)
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "run", tiny("train.steps=3", "valid.every=0", "train.rigid_loss=1",
                                       "train.unroll_steps=2"), log=quiet)
    assert read_checkpoint(tmp_path / "run" / "latest.pt")["config"]["train"]["rigid_loss"] == 1.0
    with pytest.raises(ConfigError, match="rigid_loss"):
        tiny("train.rigid_loss=-1")


def _spin_rollout(sim: LearnedSimulator, ds, steps: int):
    """A beveled cube far above the floor, spinning at SPIN, rolled out with shape matching:
    the angle turned in the last step and the rotation error at the end, degrees."""
    sc = resting_scene("beveled_cube", 1.4, ds.meshes, floor_z=0.0)
    sc.positions[:, 0, 2] = 1e3
    quat = Rotation.from_rotvec(np.outer(np.arange(sc.num_frames), SPIN)).as_quat()   # x y z w
    sc.quaternions[:, 0] = quat[:, [3, 0, 1, 2]]
    tracks = ObjectTracks([sc], MeshLibrary(ds.meshes))
    graph, verts, _ = tracks.track_vertices(torch.arange(1), 3)
    _, rots, _ = sim.rollout(verts, graph, steps, poses=True)
    last = Rotation.from_matrix(rots[-1, 0].numpy()) * Rotation.from_matrix(rots[-2, 0].numpy()).inv()
    truth = Rotation.from_rotvec(SPIN * (2 + steps))
    error = (Rotation.from_matrix(rots[-1, 0].numpy()) * truth.inv()).magnitude()
    return math.degrees(last.magnitude()), math.degrees(error)


def test_with_the_rigid_prior_a_body_free_of_forces_keeps_its_spin(movi):
    ds, scenes = movi
    spin = math.degrees(np.linalg.norm(SPIN))
    turn, error = _spin_rollout(_force_free(ds, scenes, "rigid"), ds, steps=200)
    assert abs(turn - spin) < 1e-6 and error < 1e-6, (turn, error)
    # the paper's straight-line prior needs the network to add the centripetal part: without it
    # shape matching bleeds spin away every step
    turn, error = _spin_rollout(_force_free(ds, scenes, "linear"), ds, steps=200)
    assert turn < 0.5 * spin, turn


def test_the_prior_is_a_checked_config_key():
    with pytest.raises(ConfigError, match="inertial_prior"):
        build_config(path="configs/gns_tiny.toml", overrides=["model.inertial_prior=angular"])


@pytest.mark.filterwarnings("ignore:outside training")
def test_fine_tuning_may_switch_to_the_rigid_prior_and_the_model_keeps_it(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "plain", tiny(*small), log=quiet)
    train(data, tmp_path / "rigid", tiny(*small, "model.inertial_prior=rigid", f"train.init_from={tmp_path / 'plain'}"),
          log=quiet)
    assert read_checkpoint(tmp_path / "rigid" / "latest.pt")["config"]["model"]["inertial_prior"] == "rigid"
    rigid, plain = gns.load(tmp_path / "rigid"), gns.load(tmp_path / "plain")
    assert rigid.simulator.inertial_prior == "rigid" and plain.simulator.inertial_prior == "linear"
    out = rigid.rollout(shapes=["cube"], positions=[[0.0, 0.0, 2.0]], quaternions=[[1.0, 0.0, 0.0, 0.0]],
                        velocities=[[1.0, 0.0, 0.0]], angular_velocities=[[0.0, 3.0, 0.0]], steps=5)
    assert torch.isfinite(out.positions).all()
    # a resumed run may not change it, and an ensemble may not mix priors
    with pytest.raises(CheckpointError, match="inertial_prior"):
        train(data, tmp_path / "plain", tiny("train.steps=8", "valid.every=0", "features.normalizer_steps=2",
                                             "model.inertial_prior=rigid"), resume=True, log=quiet)
    with pytest.raises(ValueError, match="inertial prior"):
        rigid.simulator.set_ensemble([plain.simulator])
