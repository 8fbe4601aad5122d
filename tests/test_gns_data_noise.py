"""Training noise of the paper's Figure 7 (on the cube's corners and on its tracked pose)."""
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen.contactnets import read_experiment, read_toss, toss_to_scene
from datagen.scenes import get_shape
from gns.config import ConfigError, build_config
from gns.data import ObjectTracks
from gns.graph import MeshLibrary

SRC = Path(__file__).parent / "data" / "contactnets"
CUBE = get_shape("cube")


@pytest.fixture(scope="module")
def tracks():
    consts = read_experiment(SRC)
    scenes = [toss_to_scene(read_toss(SRC / "tosses_processed" / f"{i}.pt"), i, f"{i}.pt", consts) for i in (55, 229)]
    return ObjectTracks(scenes, MeshLibrary({"cube": (CUBE.vertices, CUBE.faces)}))


def windows(tracks, n=400, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).integers(0, tracks.num_windows, n))


def frames(batch):
    return torch.cat([batch.history, batch.target[:, None]], dim=1)  # (N, 4, 3)


def body_frame(tracks, w, x):
    """World vertices (N, 4, 3) of windows w -> body-frame offsets from the pose's centre."""
    pos, rot = tracks.poses(tracks.window_track[w], tracks.window_first[w], 4)
    node_graph = tracks.graph(tracks.window_track[w]).node_graph
    return torch.einsum("ntji,ntj->nti", rot[node_graph], x - pos[node_graph])


def test_config_keys_default_to_off_and_refuse_negative_values():
    cfg = build_config()
    assert cfg.augment.vertex_noise == 0.0 and cfg.augment.track_noise == 0.0
    cfg = build_config(overrides=["augment.vertex_noise=0.05", "augment.track_noise=0.5"])
    assert (cfg.augment.vertex_noise, cfg.augment.track_noise) == (0.05, 0.5)
    for key in ("vertex_noise", "track_noise"):
        with pytest.raises(ConfigError, match=key):
            build_config(overrides=[f"augment.{key}=-0.1"])


def test_vertex_noise_is_one_body_frame_offset_per_corner_scaled_by_the_size(tracks):
    w = windows(tracks)
    clean = frames(tracks.batch(w))
    noisy = frames(tracks.batch(w, np.random.default_rng(1), vertex_noise=0.05))
    offset = body_frame(tracks, w, noisy) - body_frame(tracks, w, clean)   # (N, 4, 3)
    torch.testing.assert_close(offset, offset[:, :1].expand_as(offset), atol=1e-9, rtol=0)  # fixed over the window
    std = float(offset[:, 0].std())
    assert std == pytest.approx(0.05 * 2.0, rel=0.1)  # the cube is 2 half-widths wide
    again = frames(tracks.batch(w, np.random.default_rng(2), vertex_noise=0.05))
    assert not torch.allclose(again, noisy)  # a new offset for every window


def test_track_noise_moves_the_whole_cube_by_a_fraction_of_its_per_frame_motion(tracks):
    w = windows(tracks, 600)
    clean = frames(tracks.batch(w))
    noisy = frames(tracks.batch(w, np.random.default_rng(3), track_noise=0.5))
    shift = noisy - clean                                                   # (N, 4, 3)
    graph = tracks.graph(tracks.window_track[w])
    counts = torch.bincount(graph.node_graph, minlength=graph.num_graphs)
    first = torch.cumsum(counts, 0) - counts                                # first node of each graph
    torch.testing.assert_close(shift, shift[first][graph.node_graph], atol=1e-9, rtol=0)  # rigid translation
    per_graph = shift[first]                                                # (B, 4, 3)
    pos, _ = tracks.poses(tracks.window_track[w], tracks.window_first[w], 4)
    step = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1)                          # (B, 3)
    disp = torch.cat([step[:, :1], step], dim=1)                            # (B, 4): frame 0 uses the next step
    z = per_graph / (0.5 * disp[..., None]).clamp_min(1e-12)
    moving = disp > 1e-3
    assert float(z[moving].std()) == pytest.approx(1.0, rel=0.1)           # std = 0.5 x displacement
    assert (~moving).any() and float(per_graph[~moving].abs().max()) < 6 * 0.5e-3  # a still cube barely moves
    assert not torch.allclose(per_graph[:, 0], per_graph[:, 1])             # independent per frame

