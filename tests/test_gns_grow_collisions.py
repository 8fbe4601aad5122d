"""Collision edges grown onto a model trained on single objects (train.init_from on data of
several objects a scene): the start predicts exactly what the single-object model predicts,
collision edges or not, and training then changes it."""
from dataclasses import replace

import pytest
import torch

from datagen.toss import generate
from datagen.scenes import load_config
from gns.checkpoint import CheckpointError, build_simulator, read_checkpoint
from gns.data import load_data
from gns.fine_tune import init_from
from gns.train import train
from test_gns_train import quiet, tiny


def _toss(out, objects: str, seed: int):
    cfg = load_config(None, ["scene.frames=8", "scene.shapes=['beveled_cube', 'sphere']", f'scene.objects="{objects}"'])
    generate(cfg, seed, {"train": 4, "valid": 0, "test": 0}, out, progress=False)
    return out


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    root = tmp_path_factory.mktemp("grow")
    data = _toss(root / "single", "1", 0)
    train(data, root / "run", tiny("train.steps=3", "valid.every=0", "features.centre_node=true"), log=quiet)
    return root


def test_a_grown_model_starts_as_the_single_object_model_and_then_learns_contacts(single):
    multi = _toss(single / "multi", "3-4", 1)
    cfg = tiny("train.steps=2", "valid.every=0", "features.centre_node=true", "features.collision_radius=3.0",
               f"train.init_from={single / 'run'}")
    spec, tracks, _ = load_data(multi, cfg)
    assert spec.collision_edges
    grown = build_simulator(cfg, spec)
    spec = replace(spec, node_features=tuple(n for n, _ in grown.layout.node_groups),   # as training sets them
                   edge_features=tuple(n for n, _ in grown.layout.edge_groups),
                   collision_features=tuple(n for n, _ in grown.layout.collision_groups))
    init_from(grown, str(single / "run"), cfg, spec)
    plain = build_simulator(tiny("features.centre_node=true"), spec.__class__.from_dict(
        read_checkpoint(single / "run" / "latest.pt")["spec"]))
    plain.load_state_dict(read_checkpoint(single / "run" / "latest.pt")["model"])
    assert grown.layout.collisions and not plain.layout.collisions
    batch = tracks.batch(torch.arange(tracks.num_windows))
    grown.eval(), plain.eval()
    with torch.no_grad():
        edges = grown.collision_edges(batch.history[:, -1], batch.graph)
        assert edges.senders.numel() > 0          # the scenes hold contacts: the new edges are used
        torch.testing.assert_close(grown(batch.history, batch.graph), plain(batch.history, batch.graph),
                                   rtol=0, atol=0)
    # the widened first layer of each node update: trained columns, then zeros for collisions
    w = grown.network.blocks[0].node_mlp[0].weight
    assert torch.count_nonzero(w[:, 2 * w.shape[1] // 3:]) == 0
    # a training from there moves the collision columns off zero
    train(multi, single / "grown", cfg, log=quiet)
    w = read_checkpoint(single / "grown" / "latest.pt")["model"]["network.blocks.0.node_mlp.0.weight"]
    assert torch.count_nonzero(w[:, 2 * w.shape[1] // 3:]) > 0


def test_a_model_with_another_architecture_is_refused_in_one_line(single):
    multi = single / "multi"
    if not multi.exists():
        _toss(multi, "3-4", 1)
    cfg = tiny("train.steps=1", "valid.every=0", "model.latent_size=8", f"train.init_from={single / 'run'}")
    with pytest.raises(CheckpointError, match="init_from"):
        train(multi, single / "other", cfg, log=quiet)


def test_collisions_only_keeps_every_trained_weight_and_learns_the_collision_parts(single):
    multi = single / "multi"
    if not multi.exists():
        _toss(multi, "3-4", 1)
    cfg = tiny("train.steps=3", "valid.every=0", "features.centre_node=true", "features.collision_radius=3.0",
               f"train.init_from={single / 'run'}", "train.collisions_only=true", "train.checkpoint_every=2")
    train(multi, single / "only", cfg, log=quiet)
    old = read_checkpoint(single / "run" / "latest.pt")["model"]
    new = read_checkpoint(single / "only" / "latest.pt")["model"]
    moved = set()
    for key, value in new.items():
        if key not in old:
            moved.add(key)
            continue
        kept = value[:, :old[key].shape[1]] if value.shape != old[key].shape else value
        torch.testing.assert_close(kept, old[key], rtol=0, atol=0, msg=key)
        if value.shape != old[key].shape and torch.count_nonzero(value[:, old[key].shape[1]:]) > 0:
            moved.add(key)
    assert any(".node_mlp.0.weight" in k for k in moved) and any("collision_encoder" in k for k in moved)
    # resumed to more steps, the same weights stay frozen
    more = tiny("train.steps=4", "valid.every=0", "features.centre_node=true", "features.collision_radius=3.0",
                f"train.init_from={single / 'run'}", "train.collisions_only=true", "train.checkpoint_every=2")
    train(multi, single / "only", more, log=quiet, resume=True)
    again = read_checkpoint(single / "only" / "latest.pt")
    assert again["step"] == 4
    torch.testing.assert_close(again["model"]["network.decoder.0.weight"], old["network.decoder.0.weight"], rtol=0, atol=0)


def test_collisions_only_without_a_start_is_refused():
    from gns.config import ConfigError
    with pytest.raises(ConfigError, match="collisions_only needs train.init_from"):
        tiny("train.collisions_only=true")


def test_windows_with_objects_near_each_other_are_those_whose_bounding_spheres_touch(single):
    import numpy as np
    from datagen.shards import Dataset
    from gns.data import HISTORY
    multi = single / "multi"
    if not multi.exists():
        _toss(multi, "3-4", 1)
    cfg = tiny("features.centre_node=true", "train.contact_fraction=0.5", "train.contact_kind=objects")
    _, tracks, _ = load_data(multi, cfg)
    scenes = Dataset(multi).load("train")
    meshes = Dataset(multi).meshes
    want = []
    for sc in scenes:
        r = np.array([np.linalg.norm(meshes[s][0], axis=1).max() for s in sc.shape]) * sc.scale
        d = np.linalg.norm(sc.positions[:, :, None] - sc.positions[:, None], axis=-1) - (r[:, None] + r[None])
        d[:, np.arange(sc.num_objects), np.arange(sc.num_objects)] = np.inf
        near = (d < 0).any(axis=(1, 2))
        want += [near[f + HISTORY - 1:f + tracks.window - 1].any() for f in range(sc.num_frames - tracks.window + 1)]
    assert tracks.contact.tolist() == want and 0 < sum(want) < len(want)
    _, alone, _ = load_data(single / "single", cfg)
    assert not alone.contact.any()
