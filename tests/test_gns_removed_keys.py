"""Config keys removed in rigid-gns 0.2: a checkpoint that holds one at its old default loads as
before, one that set it is refused in one line, and a config file or --set naming one is an
unknown key."""
import re

import pytest
import torch
from gns_fixtures import write_toss_dataset

from gns.checkpoint import CheckpointError, load_model, read_checkpoint
from gns.config import REMOVED, ConfigError, build_config, known_keys
from gns.train import train
from test_gns_train import quiet, tiny


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("removed")
    data = write_toss_dataset(root / "data", train=2, valid=1, frames=8)
    train(data, root / "run", tiny("train.steps=2", "valid.every=0"), log=quiet)
    return data, read_checkpoint(root / "run" / "latest.pt")


def with_key(ckpt: dict, name: str, value) -> dict:
    section, key = name.split(".")
    config = {s: dict(v) for s, v in ckpt["config"].items()}
    config[section][key] = value
    return {**ckpt, "config": config}


def test_no_removed_key_is_a_config_key():
    assert not set(REMOVED) & set(known_keys())


def test_a_checkpoint_holding_removed_keys_at_their_defaults_loads_as_without_them(trained):
    _, ckpt = trained
    old = ckpt
    for name, value in REMOVED.items():   # as every checkpoint of rigid-gns 0.1 holds them
        old = with_key(old, name, value)
    sim, cfg = load_model(old)
    plain, plain_cfg = load_model(ckpt)
    assert cfg == plain_cfg
    assert sim.state_dict().keys() == plain.state_dict().keys()
    assert all(torch.equal(a, plain.state_dict()[k]) for k, a in sim.state_dict().items())


@pytest.mark.parametrize("name, value", [("features.mesh_vertices", 16), ("train.teacher", "a+b"),
                                         ("model.inertial_prior", "rigid")])
def test_a_checkpoint_that_set_a_removed_key_is_refused_in_one_line(trained, tmp_path, name, value):
    data, ckpt = trained
    torch.save(with_key(ckpt, name, value), tmp_path / "old.pt")
    line = f"old.pt: this checkpoint uses {name}={value!r}, removed in rigid-gns 0.2"
    with pytest.raises(CheckpointError, match=re.escape(line)):
        load_model(tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match=re.escape(f"uses {name}={value!r}")):
        train(data, tmp_path / "tuned", tiny("train.steps=2", "valid.every=0", f"train.init_from={tmp_path / 'old.pt'}"),
              log=quiet)
    assert not (tmp_path / "tuned" / "latest.pt").exists()


@pytest.mark.parametrize("name", sorted(REMOVED))
def test_a_removed_key_given_with_set_is_an_unknown_key(name):
    with pytest.raises(ConfigError, match=f"unknown config key '{name}'"):
        build_config(overrides=[f"{name}=1"])
