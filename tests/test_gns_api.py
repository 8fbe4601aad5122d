"""The Python API (gns.load, Model.rollout, Model.step) against the CLI rollout, and its promises."""
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import gns
from datagen.cli import main as datagen_main
from datagen.shards import Dataset, Scene, write_metadata, write_shard
from plumbing import DataError
from gns.api import history_poses, matrix_to_quat, quat_to_matrix
from gns.cli import main as gns_main
from gns.config import ConfigError, build_config
from gns.checkpoint import CheckpointError, read_checkpoint
from gns.zoo import export_model
from gns.train import train

ROOT = Path(__file__).resolve().parents[1]
SMALL = ROOT / "tests" / "data" / "gns_movi_a_small.pt"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny model of 2-3 small cubes a scene (collision edges, materials vary), saved with its meshes."""
    tmp = tmp_path_factory.mktemp("api")
    assert datagen_main(["toss", "--out", str(tmp / "data"), "--objects", "2-3", "--scenes", "4", "--frames", "8",
                         "--shapes", "cube,cylinder", "--sizes", "small", "--quiet"]) == 0
    cfg = build_config(path="gns_tiny", overrides=["train.steps=10", "valid.every=0", "train.checkpoint_every=10"])
    train(tmp / "data", tmp / "run", cfg, log=lambda _: None)
    return tmp


def three_cubes():
    """Three small cubes side by side, 0.05 apart (within the collision radius), tossed and spinning."""
    return dict(shapes=["cube", "cylinder", "cube"], scales=0.7, friction=[0.4, 0.8, 0.4], restitution=[0.3, 0.7, 0.3],
                positions=[[0.0, 0.0, 1.0], [0.75, 0.0, 1.0], [1.5, 0.0, 1.0]],
                quaternions=[[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.0, 0.3], [0.7, 0.0, 0.7, 0.0]],
                velocities=[[1.0, 0.0, 2.0], [-1.0, 0.0, 1.0], [0.0, 0.5, 0.0]],
                angular_velocities=[[0.0, 0.0, 3.0], [1.0, 0.0, 0.0], [0.0, -2.0, 1.0]])


def test_load_returns_the_checkpoints_physics_and_meshes(run):
    model = gns.load(run / "run")
    ckpt = read_checkpoint(run / "run" / "latest.pt")
    data = Dataset(run / "data")
    assert model.frame_rate == data.frame_rate and model.dt == pytest.approx(1 / data.frame_rate)
    np.testing.assert_array_equal(model.gravity, data.gravity)
    assert model.uses_materials and model.collisions and model.shapes == ["cube", "cylinder"]
    assert set(ckpt["spec"]["meshes"]) == set(data.meshes)            # the checkpoint holds the meshes
    for name, (v, f) in data.meshes.items():
        np.testing.assert_array_equal(model.meshes[name][0], v)
        np.testing.assert_array_equal(model.meshes[name][1], f)
    # an export keeps them: a model file alone rolls out
    exported = export_model(run / "run" / "latest.pt", run / "model.pt", overwrite=True)
    assert set(read_checkpoint(exported)["spec"]["meshes"]) == set(data.meshes)
    assert gns.load(exported).meshes.keys() == model.meshes.keys()


def test_shipped_and_old_models_find_their_meshes_by_name():
    model = gns.load("real_cubes")
    assert model.frame_stride == 8 and model.dt == pytest.approx(8 / 148.0)       # the model's step, stride included
    assert model.meshes["cube"][0].shape == (8, 3) and not model.uses_materials
    assert set(gns.load(SMALL).meshes) == {"beveled_cube", "cylinder", "sphere"}


def test_an_old_checkpoint_of_an_unknown_shape_is_one_line(tmp_path):
    ckpt = torch.load(SMALL, weights_only=True)
    ckpt["spec"]["shapes"] = ["teapot"]
    torch.save(ckpt, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="no meshes .* shape 'teapot' is not one of datagen's") as e:
        gns.load(tmp_path / "old.pt")
    assert "\n" not in str(e.value)
    teapot = gns.load(tmp_path / "old.pt", meshes={"teapot": (np.eye(3), [[0, 1, 2]])})
    assert list(teapot.meshes) == ["teapot"]


def test_history_is_free_flight_back_from_the_pose_and_velocity():
    # a parabola and a constant spin, sampled exactly: the history must reproduce them
    dt, g = 0.1, torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)
    p0, v0 = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64), torch.tensor([[0.5, -1.0, 4.0]], dtype=torch.float64)
    w = torch.tensor([[0.3, -0.2, 2.0]], dtype=torch.float64)
    r0 = quat_to_matrix(torch.tensor([[0.8, 0.2, -0.1, 0.5]], dtype=torch.float64))
    t = 2 * dt
    from gns.api import rotation_vector_to_matrix
    pos, rot = history_poses(p0 + v0 * t + 0.5 * g * t * t, rotation_vector_to_matrix(w * t) @ r0, v0 + g * t, w, dt, g)
    for k in range(3):
        s = k * dt
        torch.testing.assert_close(pos[k], p0 + v0 * s + 0.5 * g * s * s, rtol=0, atol=1e-12)
        torch.testing.assert_close(rot[k], rotation_vector_to_matrix(w * s) @ r0, rtol=0, atol=1e-12)


def test_quaternion_conversions_agree_with_the_numpy_ones():
    from gns.geometry import matrix_to_quat as np_matrix_to_quat, quat_to_matrix as np_quat_to_matrix
    q = np.random.default_rng(0).normal(size=(50, 4))
    np.testing.assert_allclose(quat_to_matrix(torch.from_numpy(q)).numpy(), np_quat_to_matrix(q), atol=1e-12)
    m = np_quat_to_matrix(q)
    np.testing.assert_allclose(matrix_to_quat(torch.from_numpy(m)).numpy(), np_matrix_to_quat(m), atol=1e-12)


def test_api_rollout_equals_the_cli_rollout_of_the_same_scene(run, tmp_path):
    model = gns.load(run / "run")
    s, steps = three_cubes(), 6
    api = model.rollout(**s, steps=steps)
    # the same start as a dataset scene: its first 3 frames are the history the API built
    start = model.state(**s)
    g = torch.as_tensor(model.gravity)
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    pos, rot = history_poses(t(s["positions"]), quat_to_matrix(t(s["quaternions"])), t(s["velocities"]),
                             t(s["angular_velocities"]), model.dt, g)
    torch.testing.assert_close(start.frames[0], torch.einsum("nij,nj->ni", rot[0][start.vertex_object],
                                                             start.graph.rest) + pos[0][start.vertex_object])
    T, n = 3 + steps, 3
    filler = lambda a: np.concatenate([a, np.repeat(a[-1:], steps, 0)])  # noqa: E731  frames the rollout replaces
    scene = Scene(positions=filler(pos.numpy()), quaternions=filler(matrix_to_quat(rot).numpy()),
                  velocities=np.zeros((T, n, 3)), angular_velocities=np.zeros((T, n, 3)), shape=s["shapes"],
                  material=["metal", "rubber", "metal"], scale=np.full(n, 0.7), mass=np.ones(n),
                  friction=np.array(s["friction"]), restitution=np.array(s["restitution"]))
    source = Dataset(run / "data")
    (tmp_path / "d").mkdir()
    write_shard(tmp_path / "d" / "test-00000.h5", [scene], source.meshes)
    write_metadata(tmp_path / "d", {k: v for k, v in source.meta.items() if k not in ("splits", "format_version")}
                   | {"splits": {"test": {"num_scenes": 1, "shards": ["test-00000.h5"]}}})
    assert gns_main(["rollout", "--run", str(run / "run"), "--data", str(tmp_path / "d"), "--out", str(tmp_path / "o")]) is None
    cli = Dataset(tmp_path / "o").load("test")[0]
    np.testing.assert_allclose(api.positions.numpy(), cli.positions[2:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(quat_to_matrix(api.quaternions).numpy(),
                               quat_to_matrix(torch.from_numpy(cli.quaternions[2:])).numpy(), rtol=0, atol=1e-9)
    assert api.vertices.shape == (steps + 1, start.graph.num_nodes, 3)


def test_true_past_poses_can_replace_the_velocities(run):
    model = gns.load(run / "run")
    s = three_cubes()
    from_velocity = model.rollout(**s, steps=3)
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    pos, rot = history_poses(t(s["positions"]), quat_to_matrix(t(s["quaternions"])), t(s["velocities"]),
                             t(s["angular_velocities"]), model.dt, torch.as_tensor(model.gravity))
    past = {k: v for k, v in s.items() if k not in ("velocities", "angular_velocities")}
    from_history = model.rollout(**past, history=(pos[:2], matrix_to_quat(rot[:2])), steps=3)
    torch.testing.assert_close(from_history.positions, from_velocity.positions, rtol=0, atol=1e-12)
    with pytest.raises(DataError, match="either velocities or history"):
        model.rollout(**s, history=(pos[:2], matrix_to_quat(rot[:2])), steps=1)


def test_objects_given_together_are_one_scene_and_collide(run):
    model = gns.load(run / "run")
    s = three_cubes()
    together = model.rollout(**s, steps=3)
    apart = model.rollout(**s, steps=3, scene=[0, 1, 2])
    assert not torch.allclose(together.positions[1], apart.positions[1])   # collision edges were used


def test_batched_scenes_equal_one_by_one(run):
    model = gns.load(run / "run")
    s = three_cubes()
    batched = model.rollout(**s, steps=4, scene=[0, 0, 1])
    pair = model.rollout(**{k: v[:2] if isinstance(v, list) else v for k, v in s.items()}, steps=4)
    alone = model.rollout(**{k: v[2:] if isinstance(v, list) else v for k, v in s.items()}, steps=4)
    torch.testing.assert_close(batched.positions, torch.cat([pair.positions, alone.positions], 1), rtol=0, atol=1e-6)  # float32 network: kernels may block by batch size
    torch.testing.assert_close(batched.quaternions, torch.cat([pair.quaternions, alone.quaternions], 1), rtol=0, atol=1e-6)


def test_stepping_in_a_loop_equals_the_rollout(run):
    model = gns.load(run / "run")
    s = three_cubes()
    out = model.rollout(**s, steps=3)
    state = model.state(**s)
    with torch.no_grad():
        for k in range(3):
            state = model.step(state)
            torch.testing.assert_close(state.positions, out.positions[k + 1], rtol=0, atol=0)
    assert state.time == pytest.approx(3 * model.dt)


def test_differentiable_rollout_gives_gradients_of_the_initial_velocity(run):
    model = gns.load(run / "run")
    s = three_cubes()
    v = torch.tensor(s.pop("velocities"), dtype=torch.float64, requires_grad=True)
    out = model.rollout(**s, velocities=v, steps=4, differentiable=True)
    out.positions[-1, :, 0].sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0
    # the gradient is the derivative: a small change of one velocity moves the result by it
    plain = model.rollout(**s, velocities=v.detach(), steps=4)
    torch.testing.assert_close(out.positions.detach(), plain.positions, rtol=0, atol=1e-9)
    assert not plain.positions.requires_grad
    eps = 1e-4
    nudged = v.detach().clone()
    nudged[0, 0] += eps
    moved = (model.rollout(**s, velocities=nudged, steps=4).positions[-1, :, 0].sum()
             - plain.positions[-1, :, 0].sum()) / eps
    assert float(moved) == pytest.approx(float(v.grad[0, 0]), rel=0.05, abs=1e-3)


def test_a_material_model_without_materials_is_one_line(run):
    model = gns.load(run / "run")
    s = three_cubes()
    del s["friction"]
    with pytest.raises(DataError, match="give friction= and restitution=") as e:
        model.rollout(**s, steps=1)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("bad, match", [({"shapes": ["teapot"] * 3}, "shape 'teapot' has no mesh"),
                                        ({"positions": [[0, 0, 1]] * 2}, "positions has shape"),
                                        ({"quaternions": [[0, 0, 0, 0]] * 3}, "non-zero"),
                                        ({"scene": [0, 1]}, "one scene number per object")])
def test_bad_inputs_are_one_line(run, bad, match):
    model = gns.load(run / "run")
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**{**three_cubes(), **bad}, steps=1)
    assert "\n" not in str(e.value)


def test_scipy_quaternion_order_in_and_out(run):
    wxyz, xyzw = gns.load(run / "run"), gns.load(run / "run", quaternion_order="xyzw")
    s = three_cubes()
    a = wxyz.rollout(**s, steps=2)
    b = xyzw.rollout(**{**s, "quaternions": np.array(s["quaternions"])[:, [1, 2, 3, 0]]}, steps=2)
    torch.testing.assert_close(a.positions, b.positions, rtol=0, atol=0)
    torch.testing.assert_close(a.quaternions[..., [1, 2, 3, 0]], b.quaternions, rtol=0, atol=0)
    from scipy.spatial.transform import Rotation
    np.testing.assert_allclose(Rotation.from_quat(b.quaternions[-1].numpy()).as_matrix(),
                               quat_to_matrix(a.quaternions[-1]).numpy(), atol=1e-12)


def test_inputs_outside_training_warn():
    model = gns.load("real_cubes")
    with pytest.warns(UserWarning, match="outside training: speed") as caught:
        model.rollout(shapes=["cube"], scales=2.0, positions=[[0, 0, 3]], quaternions=[[1, 0, 0, 0]],
                      velocities=[[500.0, 0, 0]], steps=1)
    assert caught[0].filename == __file__                # the warning names the caller's line
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.rollout(shapes=["cube"], scales=2.0, positions=[[0, 0, 3]], quaternions=[[1, 0, 0, 0]],
                      velocities=[[5.0, 0, 0]], steps=1)


def test_objects_of_one_scene_warn_with_a_model_without_collision_edges():
    model = gns.load("real_cubes")
    two = dict(shapes=["cube", "cube"], scales=2.0, positions=[[0, 0, 3], [5, 0, 3]], quaternions=[[1, 0, 0, 0]] * 2,
               steps=1)
    with pytest.warns(UserWarning, match="no collision edges"):
        model.rollout(**two)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.rollout(**two, scene=[0, 1])       # two scenes of one object: nothing to warn about


def test_hot_path_creates_no_tensor_off_the_inputs_device(run):
    """Every tensor of a rollout (API, features, collision edges, shape matching) follows its
    inputs' device: with the default device set to `meta`, a tensor created without device=
    lands there and the first operation mixing it with the CPU inputs fails. (What would fail
    on CUDA with CPU-made index tensors, tested without a GPU.)"""
    model = gns.load(run / "run")
    s = three_cubes()
    expected = model.rollout(**s, steps=3)
    torch.set_default_device("meta")
    try:
        out = model.rollout(**s, steps=3)
    finally:
        torch.set_default_device(None)
    torch.testing.assert_close(out.positions, expected.positions, rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA; the meta-device test covers the same path on CPU")
def test_cuda_rollout_equals_cpu(run):
    s = three_cubes()
    cpu = gns.load(run / "run").rollout(**s, steps=5)
    cuda = gns.load(run / "run", device="cuda").rollout(**s, steps=5)
    assert cuda.positions.device.type == "cuda"
    torch.testing.assert_close(cuda.positions.cpu(), cpu.positions, rtol=0, atol=1e-5)


def test_example_script_runs():
    script = ROOT / "examples" / "rollout.py"
    assert len(script.read_text().splitlines()) <= 15
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    rows = [[float(v) for v in re.findall(r"=\s*(-?[\d.]+)", line)] for line in out.stdout.splitlines()
            if line.startswith("t=")]
    assert len(rows) >= 3 and all(len(r) == 4 for r in rows), out.stdout
    _, x, y, z = zip(*rows)
    assert z[0] == 3.0 and 0.9 < z[-1] < 1.1     # tossed from 3 half-widths, it comes to rest on a face
    assert all(b >= a - 0.05 for a, b in zip(x, x[1:])) and x[-1] > 1.0   # thrown forward, it goes forward
    # a toss symmetric in y veers sideways only as far as the cube's triangulated faces (diagonals one
    # way) break the mirror: symmetrized, 0.06 half-widths; the network alone 0.16 (measured)
    assert max(abs(v) for v in y) <= 0.1


def test_a_symmetrized_model_keeps_a_mirror_symmetric_toss_in_its_plane(run):
    # an octahedron is mirror-symmetric with its edges (a cube's triangulated faces are not: each
    # face's diagonal goes one way), so a toss in the x-z plane must stay in it exactly
    octahedron = (np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 0.5,
                  np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]))
    toss = dict(shapes=["cube"], scales=0.7, positions=[[0.0, 0.0, 0.6]], quaternions=[[0.9, 0.0, 0.3, 0.0]],
                velocities=[[1.0, 0.0, 0.5]], angular_velocities=[[0.0, 3.0, 0.0]], friction=0.5, restitution=0.5,
                steps=8)
    meshes = {"cube": octahedron, "cylinder": octahedron}
    plain = gns.load(run / "run", meshes=meshes).rollout(**toss)
    sym = gns.load(run / "run", meshes=meshes, symmetrize="d2").rollout(**toss)
    assert plain.positions[1:, 0, 1].abs().max() > 1e-6       # the network alone is not mirror-symmetric
    # averaged over the floor's mirrors it is, to the rounding of float32 network outputs (which
    # differs with the row a mirror image takes in the batch: 1.3e-9 after 8 steps on one CPU)
    assert sym.positions[:, 0, 1].abs().max() < 1e-8
    with pytest.raises(ConfigError, match="symmetrize: unknown symmetry group 'd3'"):
        gns.load(run / "run", symmetrize="d3")


def test_an_ensemble_loaded_in_python_averages_its_members(run, tmp_path):
    toss = dict(shapes=["cube"], scales=0.7, positions=[[0.0, 0.0, 0.6]], quaternions=[[1.0, 0.0, 0.0, 0.0]],
                velocities=[[1.0, 0.2, 0.5]], angular_velocities=[[0.0, 3.0, 1.0]], friction=0.5, restitution=0.5)
    cfg = build_config(path="gns_tiny", overrides=["train.steps=10", "valid.every=0", "train.seed=7"])
    train(run / "data", tmp_path / "other", cfg, log=lambda _: None)
    a, b = gns.load(run / "run"), gns.load(tmp_path / "other")
    pair = gns.load(run / "run", ensemble=tmp_path / "other")
    state = a.state(**toss)
    history = torch.stack(state.frames, dim=1)
    with torch.no_grad():
        mean = (a.simulator.predict_acceleration(history, state.graph)
                + b.simulator.predict_acceleration(history, state.graph)) / 2
        torch.testing.assert_close(pair.simulator.predict_acceleration(history, state.graph), mean, rtol=0, atol=1e-9)


def test_symmetrized_images_in_one_call_equal_one_call_per_image(run):
    # scenes of several touching objects: each image keeps its own collision edges
    from dataclasses import replace

    import gns.symmetry as symmetry
    from gns.symmetry import FLOOR_SYMMETRIES
    model = gns.load(run / "run", symmetrize="d2")
    sim = model.simulator
    state = model.state(**three_cubes(), warn=False)
    history = torch.stack(state.frames, dim=1)
    batched = sim.predict_acceleration(history, state.graph)
    one = []
    for m in FLOOR_SYMMETRIES:
        g = torch.tensor(m, dtype=torch.float64).diagonal()   # the mirrors: diagonal maps
        mapped = replace(state.graph, rest=state.graph.rest * g, collision_edges=None)
        one.append(sim.target_normalizer.inverse(sim(history * g, mapped).to(torch.float64)) * g)
    torch.testing.assert_close(batched, sum(one) / 4, rtol=0, atol=1e-9)
    # and split over several calls when the images exceed a call's size
    old, symmetry.IMAGE_NODES = symmetry.IMAGE_NODES, state.graph.num_nodes
    try:
        torch.testing.assert_close(sim.predict_acceleration(history, state.graph), batched, rtol=0, atol=1e-9)
    finally:
        symmetry.IMAGE_NODES = old


def test_options_given_at_load_are_the_models_and_its_rollouts_honour_them(run):
    from dataclasses import replace

    from gns.spec import RolloutOptions
    plain = gns.load(run / "run")
    assert plain.options == RolloutOptions()   # a run folder outside the zoo: the defaults
    fast = gns.load(run / "run", free_flight=True, body_frames=True)
    assert fast.options == RolloutOptions(free_flight=True, body_frames=True)
    assert gns.load(run / "run", options=fast.options, symmetrize="d1").options.symmetrize == "d1"
    with pytest.raises(TypeError, match="unknown rollout option 'free_fligth'; known: .*free_flight"):
        gns.load(run / "run", free_fligth=True)
    # one cube high above the floor, alone: in free flight it follows the exact inertial update,
    # its centre's second difference gravity's g dt^2 to rounding, which the network never is
    toss = dict(shapes=["cube"], scales=0.7, friction=[0.5], restitution=[0.5], positions=[[0.0, 0.0, 5.0]],
                quaternions=[[0.9, 0.1, 0.0, 0.3]],
                velocities=[[1.0, 0.0, 0.0]], angular_velocities=[[0.0, 0.0, 3.0]])
    g_step = torch.as_tensor(fast.gravity, dtype=torch.float64) * fast.dt ** 2
    for model, exact in ((fast, True), (plain, False)):
        p = model.rollout(**toss, steps=4).positions.to(torch.float64)
        second = p[2:] - 2 * p[1:-1] + p[:-2]
        assert torch.allclose(second, g_step.expand_as(second), rtol=0, atol=1e-9) == exact
    # body frames: Model.rollout averages over each object's equivalent frames as gns eval's
    # rollout does (LearnedSimulator.rollout, which adds the frames to its graph itself)
    near_floor = dict(toss, positions=[[0.0, 0.0, 0.4]], velocities=[[0.0, 0.0, -1.0]])
    frames = gns.load(run / "run", body_frames=True)
    state = frames.state(**near_floor)
    assert state.graph.symmetries is not None and int(state.graph.num_symmetries[0]) == 24
    bare = replace(state.graph, symmetries=None, num_symmetries=None)
    expected = frames.simulator.rollout(torch.stack(state.frames, 1), bare, 3)
    torch.testing.assert_close(frames.rollout(**near_floor, steps=3).vertices[1:], expected, rtol=0, atol=1e-12)
    # control: the averaging changes the answer
    assert not torch.allclose(plain.rollout(**near_floor, steps=3).vertices[1:], expected, rtol=0, atol=1e-9)


def test_keep_apart_pushes_leave_velocities_to_a_model_with_collision_edges_and_give_them_to_one_without(run, tmp_path):
    # with collision edges the network is the contact's response: the push that takes objects out of
    # each other translates the frames the next step reads too, and the velocity it reads is the
    # plain step's. Without them the push is the only response and parts the objects at its speed
    assert datagen_main(["toss", "--out", str(tmp_path / "data"), "--scenes", "3", "--frames", "8",
                         "--shapes", "cube", "--sizes", "small", "--quiet"]) == 0
    train(tmp_path / "data", tmp_path / "single", build_config(path="gns_tiny", overrides=["train.steps=5", "valid.every=0"]),
          log=lambda _: None)
    start = dict(shapes=["cube", "cube"], positions=[[0.0, 0.0, 1.0], [0.42, 0.315, 1.315]], scales=0.7,
                 quaternions=[[1.0, 0.0, 0.0, 0.0]] * 2, velocities=[[1.0, 0.5, 0.0]] * 2, scene=[0, 0],
                 friction=0.5, restitution=0.5)
    for path, collisions in ((run / "run", True), (tmp_path / "single", False)):
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")      # inside each other (and, for one, no collision edges)
            steps = {k: gns.load(path, keep_apart=k) for k in (True, False)}
            assert steps[True].collisions == collisions
            apart, plain = (m.step(m.state(**start)) for m in (steps[True], steps[False]))
        push = apart.frames[-1] - plain.frames[-1]
        assert float(push.norm(dim=-1).max()) > 0.1
        change = (apart.frames[-1] - apart.frames[-2]) - (plain.frames[-1] - plain.frames[-2])
        torch.testing.assert_close(change, torch.zeros_like(change) if collisions else push, atol=1e-9, rtol=0)
