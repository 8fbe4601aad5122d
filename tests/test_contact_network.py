"""A contact network (LearnedSimulator.set_contact_model): the objects that have a collision edge,
and their partners, move as the contact network says, every other object exactly as the model
alone moves it; it ships inside an exported model, and one that reads other graphs is refused."""
from dataclasses import replace

import pytest
import torch
from gns_fixtures import rolled_out
from test_gns_lowest_vertices import _simulator, _stacked_scene
from test_gns_train import tiny

from gns.checkpoint import CheckpointError, CONTACT, build_simulator, load_model, read_checkpoint
from gns.cli import main as gns_main
from gns.config import config_to_dict
from gns.fine_tune import init_from
from gns.graph import select_graphs
from gns.spec import Floor, ModelSpec
from gns.zoo import export_model


def _history(x_t):
    """Three frames falling 2 cm a frame onto x_t, (N, 3, 3)."""
    return torch.stack([x_t + torch.tensor([0.0, 0.0, 0.02 * k], dtype=torch.float64) for k in (2, 1, 0)], 1)


def _pair(seed=1):
    """(model, contact network): the same graphs, other weights."""
    base = _simulator(6, collisions=True).eval()
    torch.manual_seed(seed)
    for p in (other := _simulator(6, collisions=True).eval()).network.parameters():
        torch.nn.init.normal_(p, std=0.3)
    return base, other


def test_objects_in_contact_take_the_contact_networks_acceleration_and_the_others_the_models():
    base, contact = _pair()
    x_t, graph = _stacked_scene()   # scene 0: sphere, cube on it, a cube 3 away; scene 1: a sphere alone
    history = _history(x_t)
    with torch.no_grad():
        alone = base.predict_acceleration(history, graph)
        theirs = contact.predict_acceleration(history, graph)
        base.set_contact_model(contact)
        both = base.predict_acceleration(history, graph)
    touching = torch.isin(graph.node_graph, torch.tensor([0, 1]))
    torch.testing.assert_close(both[touching], theirs[touching])
    torch.testing.assert_close(both[~touching], alone[~touching])
    assert not torch.allclose(both[touching], alone[touching], rtol=0.1, atol=0)   # the two networks differ there


def test_a_scene_without_contact_rolls_out_exactly_as_the_model_alone():
    base, contact = _pair()
    x_t, graph = _stacked_scene()
    # the far cube and the lone sphere
    sub, nodes = select_graphs(graph, torch.tensor([False, False, True, True]))
    history = _history(x_t)[nodes]
    with torch.no_grad():
        alone = rolled_out(base, history, sub, 6)
        base.set_contact_model(contact)
        both = rolled_out(base, history, sub, 6)
    assert torch.equal(alone, both)


def _laid_out(sim, spec):
    """spec with sim's feature layout, as training writes it."""
    return replace(spec, **{f"{k}_features": tuple(n for n, _ in getattr(sim.layout, f"{k}_groups"))
                            for k in ("node", "edge", "collision")})


def _save(sim, cfg, spec, path):
    """sim as a checkpoint file."""
    spec = _laid_out(sim, spec)
    torch.save({"format": 1, "step": 3, "seed": 0, "config": config_to_dict(cfg), "spec": spec.to_dict(),
                "model": sim.state_dict(), "provenance": {}}, path)
    return path


def test_an_exported_model_carries_its_contact_network_and_refuses_one_of_other_graphs(tmp_path, capsys):
    spec = ModelSpec(floor=Floor(z=0.0), frame_rate=12.0, gravity=(0.0, 0.0, -10.0), collision_edges=True)
    overrides = ("features.lowest_vertices=6", "features.centre_node=true", "features.surface_edges=false",
                 "features.collision_mode=vertex")
    cfg = tiny(*overrides)
    base, contact = _pair()
    a, b = _save(base, cfg, spec, tmp_path / "a.pt"), _save(contact, cfg, spec, tmp_path / "b.pt")
    gns_main(["export", "--run", str(a), "--contact", str(b), "--out", str(tmp_path / "m.pt")])
    assert "with its contact network" in capsys.readouterr().out
    saved = read_checkpoint(tmp_path / "m.pt")
    assert set(saved[CONTACT]) >= {"config", "spec", "model"} and "optimizer" not in saved[CONTACT]
    loaded, _ = load_model(tmp_path / "m.pt")
    x_t, graph = _stacked_scene()
    with torch.no_grad():
        base.set_contact_model(contact)
        torch.testing.assert_close(loaded.predict_acceleration(_history(x_t), graph),
                                   base.predict_acceleration(_history(x_t), graph), rtol=0, atol=0)
    # re-exported, the contact network goes along
    again = export_model(tmp_path / "m.pt", tmp_path / "m2.pt")
    assert CONTACT in read_checkpoint(again)
    # fine-tuning starts from the model's own network, and says that the contact network stays behind
    fresh = build_simulator(cfg, spec)
    with pytest.warns(UserWarning, match="carries a contact network"):
        init_from(fresh, str(tmp_path / "m.pt"), cfg, _laid_out(fresh, spec))
    assert all(torch.equal(a_, b_) for a_, b_ in zip(fresh.network.parameters(), base.network.parameters()))
    # a contact network that finds collision edges within another radius reads other graphs
    far = tiny(*overrides, "features.collision_radius=0.5")
    torch.manual_seed(0)
    c = _save(build_simulator(far, spec), far, spec, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="contact network differs from the model in its collision edges"):
        export_model(a, tmp_path / "bad.pt", contact=c)
    assert not (tmp_path / "bad.pt").exists()
    # and a model without collision edges cannot have one
    single = tiny("features.lowest_vertices=6", "features.centre_node=true", "features.surface_edges=false")
    flat = ModelSpec(floor=Floor(z=0.0), frame_rate=12.0, gravity=(0.0, 0.0, -10.0))
    s = _save(build_simulator(single, flat), single, flat, tmp_path / "s.pt")
    with pytest.raises(CheckpointError, match="needs a model with collision edges"):
        export_model(s, tmp_path / "bad.pt", contact=b)
