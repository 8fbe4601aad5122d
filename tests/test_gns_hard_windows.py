"""Windows drawn by the model's own one-step error (train.hard_fraction)."""
import numpy as np
import pytest
import torch
from gns_fixtures import cube_meshes, write_toss_dataset

from gns.config import ConfigError
from gns.data import ObjectTracks
from gns.graph import MeshLibrary
from gns.train import build_simulator, load_data, train, window_errors
from test_gns_train import metrics, quiet, tiny
from test_gns_train_levers import G_STEP, ballistic, scene


def _tracks():
    rest = np.tile([0.0, 0.0, 0.5], (10, 1))
    return ObjectTracks([scene(ballistic(10)), scene(rest), scene(ballistic(10, 30.0))], MeshLibrary(cube_meshes()))


def test_the_hard_share_is_drawn_by_weight_and_zero_leaves_the_old_draws_alone():
    tracks = _tracks()
    weights = torch.zeros(tracks.num_windows, dtype=torch.float64)
    chosen = [1, tracks.num_windows - 1]
    weights[chosen] = torch.tensor([1.0, 3.0], dtype=torch.float64)
    tracks.set_hardness(weights)
    rng = np.random.default_rng(0)
    firsts = []
    for _ in range(200):
        b = tracks.sample(rng, 4, False, 0.0, hard_fraction=1.0)
        firsts.append(b.history[0, 0].clone())
    # every window drawn is one of the two weighted ones, the second about three times as often
    ids = [int(np.argmin([float((f - tracks.batch(torch.tensor([w])).history[0, 0]).norm()) for w in chosen]))
           for f in firsts]
    assert 0.65 < np.mean(ids) < 0.85
    # hard_fraction 0 draws exactly what the sampler drew before it existed
    a = tracks.sample(np.random.default_rng(5), 6, False, 0.0)
    b = tracks.sample(np.random.default_rng(5), 6, False, 0.0, hard_fraction=0.0)
    assert torch.equal(a.history, b.history)
    with pytest.raises(ValueError, match="finite values >= 0"):
        tracks.set_hardness(torch.zeros(tracks.num_windows))
    with pytest.raises(ValueError, match="finite values >= 0"):
        tracks.set_hardness(torch.full((tracks.num_windows,), float("nan")))


@pytest.mark.filterwarnings("ignore:outside training")
def test_window_errors_are_larger_where_a_straight_line_step_misses_a_bounce(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=4, valid=0, frames=12)
    cfg = tiny("train.steps=1", "valid.every=0")
    spec, tracks, _ = load_data(data, cfg)
    sim = build_simulator(cfg, spec)
    sim.target_normalizer.std.fill_(1.0)
    # no acceleration at all: free flight misses only gravity, a bounce misses much more
    sim.predict_next = lambda x_tm2, x_tm1, x_t, graph: 2 * x_t - x_tm1
    err = window_errors(sim, tracks, torch.device("cpu"), chunk=5)
    assert err.shape == (tracks.num_windows,) and torch.isfinite(err).all() and (err > 0).all()
    tracks.mark_contacts(torch.as_tensor(spec.gravity_per_frame, dtype=torch.float64), 0.5)
    assert tracks.contact.any() and (~tracks.contact).any()
    assert float(err[tracks.contact].mean()) > 3 * float(err[~tracks.contact].mean())
    assert sim.training   # put back as it was


@pytest.mark.filterwarnings("ignore:outside training")
def test_training_with_hard_windows_runs_resumes_and_refuses_bad_values(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    cfg = tiny("train.steps=6", "valid.every=0", "train.hard_fraction=0.5", "train.hard_every=3",
               "train.checkpoint_every=3")
    train(data, tmp_path / "run", cfg, log=quiet)
    assert metrics(tmp_path / "run")[-1]["step"] == 6
    train(data, tmp_path / "run", tiny("train.steps=9", "valid.every=0", "train.hard_fraction=0.5",
                                       "train.hard_every=3", "train.checkpoint_every=3"), resume=True, log=quiet)
    assert metrics(tmp_path / "run")[-1]["step"] == 9
    with pytest.raises(ConfigError, match="train.hard_fraction must be in"):
        tiny("train.hard_fraction=1.5")
    with pytest.raises(ConfigError, match="train.hard_every must be >= 1"):
        tiny("train.hard_every=0")
