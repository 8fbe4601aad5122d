"""Features a fine-tuned model may add: the time of impact (features.impact_time, a node feature)
and the edges' relative velocity (features.edge_velocity)."""
import numpy as np
import pytest
import torch
from gns_fixtures import write_toss_dataset

import gns
from gns.features import impact_share
from gns.api import Model
from gns.train import CheckpointError, _build_model, load_data, read_checkpoint, train
from test_gns_train import quiet, tiny


def test_the_share_of_the_step_below_the_floor_follows_ballistic_flight():
    g = -0.1   # gravity's z per frame^2
    # heights now and a frame ago -> ballistic next height 2 z_t - z_tm1 + g
    z_t = torch.tensor([[1.0], [0.3], [0.3], [-0.1], [0.5], [0.2]], dtype=torch.float64)
    z_tm1 = torch.tensor([[1.1], [0.8], [0.2], [0.0], [0.9], [0.2]], dtype=torch.float64)
    share = impact_share(z_t, z_tm1, g).ravel()
    # far above: no impact; 0.3 -> -0.3: crosses half way; rising: none; below: all of it;
    # 0.5 -> 0.0 lands exactly at the end of the step; at rest at 0.2 -> 0.1: none
    torch.testing.assert_close(share, torch.tensor([0.0, 0.5, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    # a parabola that reaches the floor at a known instant: z(s) = h + v s + g s^2 / 2 with the
    # step's chord; the linear interpolation is exact for the chord's crossing
    h, v = 0.2, -0.35
    z_next = h + v + g   # per frame: 2 z_t - z_tm1 + g with z_tm1 = h - v
    expected = -z_next / (h - z_next)
    torch.testing.assert_close(impact_share(torch.tensor([h]), torch.tensor([h - v]), g), torch.tensor([expected]))
    assert 0.0 < expected < 1.0


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_fine_tuned_with_the_impact_feature_starts_as_it_was_and_learns_from_it(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "plain", tiny(*small), log=quiet)
    plain = gns.load(tmp_path / "plain")
    # the fine-tuning run's start, before any step: the plain weights, a zero column for the new input
    cfg = tiny(*small, "features.impact_time=true", f"train.init_from={tmp_path / 'plain'}")
    sim, _, spec, _, _ = _build_model(cfg, load_data(data, cfg)[0], None, np.random.default_rng(0))
    start = Model(sim.eval(), cfg, spec, plain.meshes, plain.device)
    assert [n for n, _ in start.simulator.layout.node_groups][-1] == "impact"
    kwargs = dict(shapes=["cube"], positions=[[0.0, 0.0, 1.2]], quaternions=[[0.9, 0.3, 0.2, 0.1]],
                  velocities=[[1.0, 0.0, -4.0]], steps=6)
    a, b = plain.rollout(**kwargs), start.rollout(**kwargs)
    # the cube reaches the floor within these steps, so the new input is not 0 everywhere
    z = a.vertices[..., 2:3].to(torch.float64) - plain.floor["z"]
    assert float(impact_share(z[1:], z[:-1], float(plain.gravity[2]) / plain.frame_rate ** 2).max()) > 0.5
    torch.testing.assert_close(b.positions, a.positions, rtol=0, atol=1e-9)
    # training moves the new column away from 0
    train(data, tmp_path / "impact", tiny(*small, "features.impact_time=true", f"train.init_from={tmp_path / 'plain'}"),
          log=quiet)
    w = read_checkpoint(tmp_path / "impact" / "latest.pt")["model"]["network.node_encoder.0.weight"]
    w0 = read_checkpoint(tmp_path / "plain" / "latest.pt")["model"]["network.node_encoder.0.weight"]
    assert w.shape[1] == w0.shape[1] + 1 and float(w[:, -1].abs().max()) > 0
    # a resumed run may not change its inputs
    with pytest.raises(CheckpointError, match="impact"):
        train(data, tmp_path / "plain", tiny("train.steps=8", "valid.every=0", "features.normalizer_steps=2",
                                             "features.impact_time=true"), resume=True, log=quiet)


def test_the_impact_feature_needs_a_floor_and_gravity():
    from gns.config import ConfigError, FeatureConfig
    from gns.features import make_layout
    with pytest.raises(ConfigError, match="impact_time"):
        make_layout(FeatureConfig(impact_time=True), floor_z=None, materials_vary=False, gravity_z_step=-0.1)
    with pytest.raises(ConfigError, match="impact_time"):
        make_layout(FeatureConfig(impact_time=True), floor_z=0.0, materials_vary=False)
    assert make_layout(FeatureConfig(impact_time=True), floor_z=0.0, materials_vary=False,
                       gravity_z_step=-0.1).node_groups[-1] == ("impact", 1)


def test_the_edge_velocity_is_the_change_of_each_edge_vector_and_turns_with_the_object():
    from dataclasses import replace
    from gns.config import FeatureConfig
    from gns.features import make_layout, raw_edge_features
    from gns.graph import MeshLibrary
    from datagen.shapes import get_shape
    mesh = get_shape("cube")
    lib = MeshLibrary({"c": (mesh.vertices, mesh.faces)})
    graph = lib.pack(lib.shape_ids(["c"]), torch.tensor([1.0]), torch.tensor([0.4]), torch.tensor([0.3]))
    layout = make_layout(FeatureConfig(edge_velocity=True), floor_z=0.0, materials_vary=False)
    assert layout.edge_groups[-1] == ("relative_velocity", 3)

    def turned(a):
        c, s = np.cos(a), np.sin(a)
        return graph.rest @ torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64).T

    # a cube spinning about z at 0.1 rad a frame while it flies: the feature sees the spin only
    w = 0.1
    shift = torch.tensor([0.7, -0.2, 0.3], dtype=torch.float64)
    history = torch.stack([turned(0.0), turned(w) + shift, turned(2 * w) + 2 * shift], dim=1)
    f = raw_edge_features(layout, history, graph)["relative_velocity"].to(torch.float64)
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    expected = (turned(2 * w)[r] - turned(2 * w)[s]) - (turned(w)[r] - turned(w)[s])
    torch.testing.assert_close(f, expected, rtol=0, atol=1e-6)
    still = torch.stack([graph.rest + k * shift for k in range(3)], dim=1)
    assert float(raw_edge_features(layout, still, graph)["relative_velocity"].abs().max()) < 1e-6


@pytest.mark.filterwarnings("ignore:outside training")
def test_a_model_fine_tuned_with_edge_velocities_starts_as_it_was(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    small = ("train.steps=4", "valid.every=0", "features.normalizer_steps=2")
    train(data, tmp_path / "plain", tiny(*small), log=quiet)
    plain = gns.load(tmp_path / "plain")
    cfg = tiny(*small, "features.edge_velocity=true", "features.impact_time=true",
               f"train.init_from={tmp_path / 'plain'}")
    sim, _, spec, _, _ = _build_model(cfg, load_data(data, cfg)[0], None, np.random.default_rng(0))
    start = Model(sim.eval(), cfg, spec, plain.meshes, plain.device)
    assert spec.edge_features[-1] == "relative_velocity" and spec.node_features[-1] == "impact"
    kwargs = dict(shapes=["cube"], positions=[[0.0, 0.0, 1.2]], quaternions=[[0.9, 0.3, 0.2, 0.1]],
                  velocities=[[1.0, 0.0, -4.0]], angular_velocities=[[0.0, 3.0, 1.0]], steps=6)
    torch.testing.assert_close(start.rollout(**kwargs).positions, plain.rollout(**kwargs).positions, rtol=0, atol=1e-9)
    train(data, tmp_path / "ev", tiny(*small, "features.edge_velocity=true", f"train.init_from={tmp_path / 'plain'}"),
          log=quiet)
    w = read_checkpoint(tmp_path / "ev" / "latest.pt")["model"]["network.edge_encoder.0.weight"]
    assert float(w[:, -3:].abs().max()) > 0
    # other edge features are weights of another shape: refused
    with pytest.raises(CheckpointError, match="edge_features"):
        train(data, tmp_path / "norest", tiny(*small, "features.rest_edges=false", f"train.init_from={tmp_path / 'plain'}"),
              log=quiet)
