"""Free flight in rollouts: objects out of reach of the floor and of other objects
follow the exact inertial update, and the network runs only on the others.

The bypass must (1) move a free object exactly (a parabola and a constant spin, whatever the
network's weights), (2) leave every other object's trajectory as the network alone makes it,
whatever else shares the batch, and (3) hand the network only the objects that need it.
"""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from gns_fixtures import rolled_out
from scipy.spatial.transform import Rotation

from datagen.scenes import get_shape
from gns.config import build_config
from gns.data import ObjectTracks
from gns.contacts import collision_edges
from gns.graph import EdgeSet, MeshLibrary, select_graphs
from gns.simulator import LearnedSimulator
from gns.spec import Floor, ModelSpec
from gns.stability import resting_scene
from gns.checkpoint import load_model

MODEL = Path(__file__).parent / "data" / "gns_movi_a_small.pt"
FRAME_RATE, G = 12.0, 10.0
SPEC = ModelSpec(frame_rate=FRAME_RATE, gravity=(0.0, 0.0, -G), floor=Floor(0.0), materials_vary=False)


def meshes(*names):
    return {n: (get_shape(n).vertices, get_shape(n).faces) for n in names}


def untrained(collisions=False, seed=0) -> LearnedSimulator:
    """Random weights: any answer the network gives is wrong, so an exact trajectory can only
    come from the inertial update."""
    torch.manual_seed(seed)
    cfg = build_config(path="configs/gns_tiny.toml")
    return LearnedSimulator(cfg.model, cfg.features, replace(SPEC, collision_edges=collisions)).eval()


def flying_frames(lib, graph, centre0, velocity, spin, frames):
    """Vertices (N, frames, 3) of one object in exact free flight: c(t) = c0 + v t + g t^2 / 2,
    R(t) = exp(t w) R0."""
    dt = 1.0 / FRAME_RATE
    r0 = Rotation.from_euler("xyz", [0.3, -0.7, 1.1])
    out = []
    for k in range(frames):
        t = k * dt
        rot = (Rotation.from_rotvec(np.asarray(spin) * t) * r0).as_matrix()
        c = np.asarray(centre0) + np.asarray(velocity) * t + 0.5 * np.array([0, 0, -G]) * t * t
        out.append(graph.rest.numpy() @ rot.T + c)
    return torch.from_numpy(np.stack(out, axis=1)), r0


def test_a_free_object_follows_the_parabola_and_keeps_its_spin_whatever_the_network():
    lib = MeshLibrary(meshes("beveled_cube"))
    graph = lib.pack(lib.shape_ids(["beveled_cube"]), torch.tensor([1.4], dtype=torch.float64),
                     torch.tensor([0.5]), torch.tensor([0.5]))
    steps = 40
    frames, _ = flying_frames(lib, graph, [1.0, -2.0, 500.0], [3.0, 1.0, 4.0], [0.5, -2.0, 3.0], 3 + steps)
    sim = untrained()
    pred, rot, centre = rolled_out(sim, frames[:, :3], graph, steps, free_flight=True, poses=True)
    np.testing.assert_allclose(pred.numpy(), frames[:, 3:].permute(1, 0, 2).numpy(), rtol=0, atol=1e-8)
    assert sim.rollout_counts == {"object_steps": steps, "network": 0, "free_flight": steps, "asleep": 0}
    # the same network without the bypass is nowhere near it
    plain = sim.rollout(frames[:, :3], graph, steps)
    assert float((plain - frames[:, 3:].permute(1, 0, 2)).abs().max()) > 1.0


def test_an_object_near_the_floor_enters_the_network_and_moves_as_without_the_bypass():
    torch.set_num_threads(1)
    sim, _ = load_model(MODEL)
    ms = meshes("beveled_cube", "cylinder", "sphere")
    sc = resting_scene("cylinder", 1.4, ms, floor_z=0.0)
    sc.positions[..., 2] += 0.2  # within the floor feature's reach: not free
    sc.positions[:, 0, 0] += np.arange(sc.num_frames) * 0.1
    graph, verts, _ = ObjectTracks([sc], MeshLibrary(ms)).track_vertices(torch.arange(1), 3)
    plain = sim.rollout(verts, graph, 12)
    bypass = rolled_out(sim, verts, graph, 12, free_flight=True)
    assert torch.equal(plain, bypass)
    assert sim.rollout_counts["free_flight"] == 0 and sim.rollout_counts["network"] == 12


def test_what_shares_the_batch_does_not_change_an_object_the_network_moves():
    """A sliding object rolled out alone, and in one batch with two objects flying high above
    it: the flying ones leave the network call (select_graphs renumbers the rest), and the
    sliding one's trajectory must not notice."""
    torch.set_num_threads(1)
    sim, _ = load_model(MODEL)
    ms = meshes("beveled_cube", "cylinder", "sphere")
    low = resting_scene("beveled_cube", 0.7, ms, floor_z=0.0)
    low.positions[:, 0, :2] += np.arange(low.num_frames)[:, None] * np.array([0.15, -0.05])
    scenes = [low]
    for shape in ("sphere", "cylinder"):
        high = resting_scene(shape, 1.4, ms, floor_z=0.0)
        high.positions[:, 0, 2] += 50.0 - 0.5 * G * (np.arange(high.num_frames) / FRAME_RATE) ** 2
        scenes.append(high)
    tracks = ObjectTracks(scenes, MeshLibrary(ms))
    alone_graph, alone_verts, _ = tracks.track_vertices(torch.arange(1), 3)
    alone = sim.rollout(alone_verts, alone_graph, 10)
    graph, verts, _ = tracks.track_vertices(torch.tensor([1, 0, 2]), 3)  # the low one in the middle
    mixed = rolled_out(sim, verts, graph, 10, free_flight=True)
    middle = graph.node_graph == 1
    np.testing.assert_allclose(mixed[:, middle].numpy(), alone.numpy(), rtol=0, atol=1e-9)
    assert sim.rollout_counts == {"object_steps": 30, "network": 10, "free_flight": 20, "asleep": 0}


def test_select_graphs_renumbers_nodes_edges_and_faces():
    lib = MeshLibrary(meshes("cube", "sphere"))
    graph = lib.pack(lib.shape_ids(["sphere", "cube", "cube"]), torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64),
                     torch.tensor([0.1, 0.2, 0.3]), torch.tensor([0.4, 0.5, 0.6]), graph_scene=torch.tensor([0, 0, 0]))
    x = graph.rest + torch.tensor([[-10.0, 0, 0], [0.0, 0, 0], [2.2, 0, 0]], dtype=torch.float64)[graph.node_graph]
    with_edges = type(graph)(**{**graph.__dict__, "collision_edges": collision_edges(x, graph, 0.5)})
    assert len(with_edges.collision_edges.senders)  # the two cubes touch
    sub, nodes = select_graphs(with_edges, torch.tensor([False, True, True]))
    assert sub.num_graphs == 2 and torch.equal(sub.rest, graph.rest[nodes])
    assert torch.equal(sub.node_graph, graph.node_graph[nodes] - 1)
    for old, new in ((with_edges.mesh_edges, sub.mesh_edges), (with_edges.collision_edges, sub.collision_edges)):
        kept = (graph.node_graph[old.senders] > 0) & (graph.node_graph[old.receivers] > 0)
        assert torch.equal(nodes[new.senders], old.senders[kept])
        assert torch.equal(nodes[new.receivers], old.receivers[kept])
    assert torch.equal(nodes[sub.faces], graph.faces[graph.node_graph[graph.faces[:, 0]] > 0])
    assert torch.equal(sub.material, graph.material[nodes])


def test_objects_near_each_other_stay_in_the_network_and_far_ones_leave_it():
    """Multi-object scene high above the floor: two cubes about to touch must be moved by the
    network (a collision edge may appear within the step), a third far away flies freely."""
    sim = untrained(collisions=True)
    lib = MeshLibrary(meshes("cube"))
    graph = lib.pack(lib.shape_ids(["cube"] * 3), torch.ones(3, dtype=torch.float64), torch.full((3,), .5),
                     torch.full((3,), .5), graph_scene=torch.zeros(3, dtype=torch.int64))
    dt = 1.0 / FRAME_RATE
    start = torch.tensor([[0.0, 0, 100], [1.3, 0, 100], [30.0, 0, 100]], dtype=torch.float64)
    velocity = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0.0, 0, 0]], dtype=torch.float64)
    frames = torch.stack([graph.rest + (start + velocity * k * dt)[graph.node_graph]
                          + torch.tensor([0, 0, -0.5 * G * (k * dt) ** 2], dtype=torch.float64)
                          for k in range(3)], dim=1)
    rolled_out(sim, frames, graph, 1, free_flight=True)
    assert sim.rollout_counts == {"object_steps": 3, "network": 2, "free_flight": 1, "asleep": 0}


def test_a_clearance_below_the_floor_clip_frees_an_object_that_cannot_reach_the_floor_within_the_step():
    """The floor clip (0.5 here) is where the network stops seeing the floor; with a clearance of
    0.1 an object 0.3 up that stays above 0.1 after the ballistic step flies exactly, one that
    the step would bring below 0.1 stays in the network."""
    sim = untrained()
    assert sim.free_flight_clip == 0.5
    lib = MeshLibrary(meshes("cube"))
    one = lib.pack(lib.shape_ids(["cube"]), torch.ones(1, dtype=torch.float64), torch.ones(1), torch.ones(1))
    low = float(one.rest[:, 2].min())
    dt = 1.0 / FRAME_RATE

    def frames_at(height, vz):   # no spin: the lowest vertex is the bottom face, `height` up at t
        return torch.stack([one.rest + torch.tensor([0.0, 0.0, height - low + vz * (k - 2) * dt
                                                     - 0.5 * G * ((k - 2) * dt) ** 2], dtype=torch.float64)
                            for k in range(3)], dim=1)

    slow, fast = frames_at(0.3, 0.0), frames_at(0.3, -3.0)   # bottom after the step: 0.27; -0.02
    for clearance, counts in ((None, (1, 1)), (0.1, (0, 1))):
        sim.options = replace(sim.options, free_flight=True, free_clearance=clearance)
        for history, network in zip((slow, fast), counts):
            pred = sim.rollout(history, one, 1)
            assert sim.rollout_counts["network"] == network
            if not network:   # exactly ballistic: the bottom face 0.3 - g dt^2 / 2 up, whatever the weights
                assert float(pred[0, :, 2].min()) == pytest.approx(0.3 - 0.5 * G * dt * dt, abs=1e-9)


def test_a_frozen_network_rolls_out_as_the_eager_one_for_each_member_and_trains_unfrozen():
    """Freezing bakes the weights into the compiled graph; two models of one class must not share
    one graph (each rolls out as its own eager network) nor one code object's cache (with dynamo's
    recompile limit at 1 here, as at 8 for the ninth model of a process, the second would run eager),
    and training must not run it."""
    from torch._dynamo.utils import counters
    torch.set_num_threads(1)
    ms = meshes("beveled_cube", "cylinder", "sphere")
    sc = resting_scene("cylinder", 1.4, ms, floor_z=0.0)
    sc.positions[:, 0, 0] += np.arange(sc.num_frames) * 0.1   # sliding on the floor: the network at work
    graph, history, _ = ObjectTracks([sc], MeshLibrary(ms)).track_vertices(torch.arange(1), 3)
    a, b = load_model(MODEL)[0], load_model(MODEL)[0]
    with torch.no_grad():
        b.network.decoder[-1].weight.mul_(3.0)
    eager = [m.rollout(history, graph, 4) for m in (a, b)]
    assert float((eager[0] - eager[1]).abs().max()) > 1e-3   # the two do differ
    graphs = counters["stats"]["unique_graphs"]
    with torch._dynamo.config.patch(recompile_limit=1):
        for m, want in zip((a, b), eager):
            m.set_speed(compile=True, freeze=True)
            np.testing.assert_allclose(m.rollout(history, graph, 4).numpy(), want.numpy(), rtol=0, atol=1e-5)
    assert counters["stats"]["unique_graphs"] - graphs == 2
    for m in (a, b):
        m.set_speed(compile=True)   # the unfrozen compiles (training's) get code objects of their own too
    codes = [m.__dict__[k]._orig_mod.forward.__code__ for m in (a, b) for k in ("_frozen_cache", "_compiled_cache")]
    assert len({id(c) for c in codes}) == 4
    a.train()
    a.loss(history, history[:, -1], graph).backward()
    assert all(p.grad is not None for p in a.network.parameters())


def test_sleeping_objects_stay_out_of_the_network_and_keep_their_pose():
    torch.set_num_threads(1)
    sim, _ = load_model(MODEL)
    ms = meshes("beveled_cube", "cylinder", "sphere")
    scenes = [resting_scene(s, 1.4, ms, floor_z=0.0) for s in ("beveled_cube", "cylinder", "sphere")]
    graph, verts, _ = ObjectTracks(scenes, MeshLibrary(ms)).track_vertices(torch.arange(3), 3)
    pred = rolled_out(sim, verts, graph, 20, sleep=True, free_flight=True)
    assert float((pred[-1] - verts[:, -1]).abs().max()) < 1e-12  # shape matching rounds, nothing more
    assert sim.rollout_counts == {"object_steps": 60, "network": 0, "free_flight": 0, "asleep": 60}


def test_free_flight_needs_gravity_and_frame_rate():
    cfg = build_config(path="configs/gns_tiny.toml")
    sim = LearnedSimulator(cfg.model, cfg.features, ModelSpec(floor=None, materials_vary=False)).eval()
    lib = MeshLibrary(meshes("cube"))
    graph = lib.pack(lib.shape_ids(["cube"]), torch.ones(1, dtype=torch.float64), torch.ones(1), torch.ones(1))
    with pytest.raises(ValueError, match="free flight needs the model's gravity"):
        rolled_out(sim, torch.stack([graph.rest] * 3, 1), graph, 1, free_flight=True)


# --- the speed options as a user reaches them: gns eval / rollout / train flags -------------

def test_eval_records_free_flight_bf16_and_the_share_of_object_steps(tmp_path, capsys):
    import json

    from gns_fixtures import write_toss_dataset
    from gns.cli import main
    data = str(write_toss_dataset(tmp_path / "d", train=2, valid=3, frames=12))
    out = {}
    for name, extra in (("plain", []), ("fast", ["--free-flight", "--autocast", "bf16"]),
                        ("near", ["--free-flight", "--free-clearance", "0.05"])):
        main(["eval", "--run", str(MODEL), "--data", data, "--split", "valid", "--json", str(tmp_path / f"{name}.json"),
              *extra])
        out[name] = json.loads((tmp_path / f"{name}.json").read_text())
    text = capsys.readouterr().out
    assert "object-steps through the network: " in text
    fast, plain = out["fast"], out["plain"]
    assert fast["free_flight"] and fast["autocast"] == "bf16" and not plain["free_flight"]
    assert plain["object_steps"]["network"] == plain["object_steps"]["object_steps"] == 3 * 9
    assert fast["object_steps"]["free_flight"] > 0  # the fixture's cubes start 1.5-3 units up
    assert fast["object_steps"]["network"] + fast["object_steps"]["free_flight"] == 3 * 9
    # a clearance below the model's floor clip: recorded, and no more object-steps in the network
    near = out["near"]
    assert fast["free_clearance"] == pytest.approx(0.5) and near["free_clearance"] == 0.05  # the clip, 0.5
    assert near["object_steps"]["network"] <= fast["object_steps"]["network"]


def test_free_clearance_needs_free_flight_and_a_height(tmp_path, capsys):
    from gns_fixtures import write_toss_dataset
    from gns.cli import main
    data = str(write_toss_dataset(tmp_path / "d", train=2, valid=1, frames=8))
    for extra, message in ((["--free-clearance", "0.2"], "--free-clearance sets free flight's height: it needs "
                                                         "--free-flight"),
                           (["--free-flight", "--free-clearance", "-1"], "--free-clearance must be a finite height "
                                                                           ">= 0 above the floor, got -1")):
        with pytest.raises(SystemExit):
            main(["eval", "--run", str(MODEL), "--data", data, "--split", "valid", *extra])
        assert message in capsys.readouterr().err


def test_a_compiled_network_rolls_out_as_the_eager_one():
    sim = untrained()
    lib = MeshLibrary(meshes("cube"))
    graph = lib.pack(lib.shape_ids(["cube", "cube"]), torch.tensor([1.0, 2.0], dtype=torch.float64),
                     torch.full((2,), .5), torch.full((2,), .5))
    frames, _ = flying_frames(lib, lib.pack(lib.shape_ids(["cube"]), torch.ones(1, dtype=torch.float64),
                                            torch.ones(1), torch.ones(1)), [0, 0, 0.8], [1, 0, 0], [0, 1, 0], 3)
    history = torch.cat([frames, frames * 2 + 0.5], dim=0)[: graph.num_nodes]
    eager = sim.rollout(history, graph, 4)
    sim.set_speed(compile=True)
    compiled = sim.rollout(history, graph, 4)
    assert "_compiled" not in dict(sim.named_modules())  # checkpoints keep their keys
    np.testing.assert_allclose(compiled.numpy(), eager.numpy(), rtol=0, atol=1e-5)


def test_train_with_compile_and_bf16_writes_a_checkpoint_that_loads_uncompiled(tmp_path):
    from gns_fixtures import write_toss_dataset
    from gns.cli import main
    from gns.checkpoint import read_checkpoint
    data = str(write_toss_dataset(tmp_path / "d", train=3, valid=1, frames=8))
    main(["train", "--data", data, "--out", str(tmp_path / "r"), "--config", "gns_tiny", "--steps", "3",
          "--compile", "--autocast", "bf16", "--set", "valid.every=0"])
    saved = read_checkpoint(tmp_path / "r" / "latest.pt")
    assert saved["config"]["train"]["compile"] is True and saved["step"] == 3
    sim, _ = load_model(saved)  # keys of the plain network: nothing of the compiled wrapper
    assert all("_orig_mod" not in k for k in saved["model"])


def test_signed_floor_distance_shows_how_deep_a_vertex_is_below_the_floor():
    from gns.network import raw_node_features
    lib = MeshLibrary(meshes("cube"))
    graph = lib.pack(lib.shape_ids(["cube"]), torch.ones(1, dtype=torch.float64), torch.ones(1), torch.ones(1))
    x = graph.rest + torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64)  # bottom face 0.3 below the floor
    history = torch.stack([x, x, x], dim=1)
    for signed, bottom in ((False, 0.0), (True, -0.3)):
        cfg = build_config(path="configs/gns_tiny.toml", overrides=[f"features.floor_signed={signed}",
                                                                      "features.floor_clip=0.5"])
        sim = LearnedSimulator(cfg.model, cfg.features, replace(SPEC, collision_edges=False))
        floor = raw_node_features(sim.layout, history, graph)["floor"][:, 0]
        assert float(floor.min()) == pytest.approx(bottom, abs=1e-6)
        assert float(floor.max()) == pytest.approx(0.5)  # the top face (0.7 up) is clipped


def test_the_python_api_rolls_out_with_free_flight_exactly_in_the_air():
    import gns
    from gns.spec import RolloutOptions
    model = gns.load(MODEL, options=RolloutOptions(free_flight=True))
    g = model.spec.gravity[2]
    out = model.rollout(["sphere"], positions=[[0.0, 0.0, 100.0]], quaternions=[[1.0, 0, 0, 0]],
                        velocities=[[1.0, 0.0, 0.0]], steps=6, scales=1.4, friction=[0.4], restitution=[0.3])
    t = torch.arange(7, dtype=torch.float64) * model.dt
    np.testing.assert_allclose(out.positions[:, 0, 2].numpy(), (100.0 + 0.5 * g * t ** 2).numpy(), atol=1e-9)
    np.testing.assert_allclose(out.positions[:, 0, 0].numpy(), t.numpy(), atol=1e-9)


def test_with_few_objects_free_the_network_runs_on_all_and_the_free_ones_still_fly_exactly():
    """Below SUBGRAPH_MIN_SHARE of the nodes left out, one call on the whole batch is cheaper
    than cutting it: the free object's rows are replaced by the inertial update, the others'
    answers are the plain rollout's."""
    from gns.stepping import SUBGRAPH_MIN_SHARE
    torch.set_num_threads(1)
    sim, _ = load_model(MODEL)
    ms = meshes("beveled_cube", "cylinder", "sphere")
    scenes = []
    for k in range(6):
        low = resting_scene("beveled_cube", 0.7, ms, floor_z=0.0)
        low.positions[:, 0, :2] += np.arange(low.num_frames)[:, None] * np.array([0.1 * k, -0.05])
        scenes.append(low)
    high = resting_scene("sphere", 0.7, ms, floor_z=0.0)
    high.positions[:, 0, 2] += 50.0 - 0.5 * G * (np.arange(high.num_frames) / FRAME_RATE) ** 2
    scenes.append(high)
    graph, verts, _ = ObjectTracks(scenes, MeshLibrary(ms)).track_vertices(torch.arange(7), 3)
    assert int((graph.node_graph == 6).sum()) < SUBGRAPH_MIN_SHARE * graph.num_nodes
    plain = sim.rollout(verts, graph, 5)
    mixed = rolled_out(sim, verts, graph, 5, free_flight=True)
    assert sim.rollout_counts == {"object_steps": 35, "network": 35, "free_flight": 5, "asleep": 0}
    low_nodes = graph.node_graph < 6
    assert torch.equal(mixed[:, low_nodes], plain[:, low_nodes])
    t = (np.arange(3, 8)) / FRAME_RATE
    z = mixed[:, ~low_nodes, 2].mean(1).numpy() - verts[~low_nodes, 0, 2].mean().item() + 50.0
    np.testing.assert_allclose(z, 50.0 - 0.5 * G * t ** 2, atol=1e-8)
