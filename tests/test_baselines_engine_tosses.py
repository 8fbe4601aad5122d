"""Engine tosses from perturbed starts of real tosses (pretraining data), and fine-tuning from them."""
from pathlib import Path

import numpy as np
import pytest
import torch

from baselines.identify import lowest_corner_height
from baselines.pybullet import PUBLISHED
from baselines.toss import FRAME_RATE, GRAVITY, initial_state
from gns.network import HISTORY
from datagen.contactnets import read_experiment, read_toss, toss_to_scene
from baselines.engine_tosses import engine_tosses

SRC = Path(__file__).parent / "data" / "contactnets"


@pytest.fixture(scope="module")
def templates():
    consts = read_experiment(SRC)
    return [toss_to_scene(read_toss(SRC / "tosses_processed" / f"{i}.pt"), i, f"{i}.pt", consts) for i in (55, 229, 274)]


def test_engine_tosses_are_deterministic_start_in_free_flight_above_the_table_and_come_to_rest(templates):
    a = engine_tosses(templates, "pybullet", PUBLISHED, 6, seed=3, frame_rate=FRAME_RATE, gravity=GRAVITY)
    b = engine_tosses(templates, "pybullet", PUBLISHED, 6, seed=3, frame_rate=FRAME_RATE, gravity=GRAVITY)
    c = engine_tosses(templates, "pybullet", PUBLISHED, 6, seed=4, frame_rate=FRAME_RATE, gravity=GRAVITY)
    assert all(np.array_equal(x.positions, y.positions) for x, y in zip(a, b))
    assert not all(np.array_equal(x.positions[:HISTORY], y.positions[:HISTORY]) for x, y in zip(a, c))
    lengths = {t.num_frames for t in templates}
    for s in a:
        assert s.num_frames in lengths and np.isfinite(s.positions).all()
        # the given frames are exact free flight: the start estimate recovers a ballistic velocity
        p, q, v, w = initial_state(s, FRAME_RATE, GRAVITY)
        dt = 1 / FRAME_RATE
        assert np.allclose(s.positions[HISTORY - 2, 0], p - v * dt + 0.5 * np.array([0, 0, -GRAVITY]) * dt ** 2)
        height = lowest_corner_height(s)
        assert height[:HISTORY].min() > 0                       # starts above the table
        assert height.min() > -0.05                           # the engine keeps it out of the table
        # by the end it has landed: its lowest corner is on the table
        assert abs(height[-1]) < 0.05


def test_starts_are_turned_templates(templates):
    """With no random orientation and no speed jitter, each start is a template's start turned
    about the vertical: same height, same speed."""
    out = engine_tosses(templates, "pybullet", PUBLISHED, 8, seed=0, frame_rate=FRAME_RATE, gravity=GRAVITY,
                        random_orientation=0.0, speed_jitter=0.0)
    starts = [initial_state(t, FRAME_RATE, GRAVITY) for t in templates]
    for s in out:
        p, _, v, w = initial_state(s, FRAME_RATE, GRAVITY)
        match = [k for k, (p0, _, v0, w0) in enumerate(starts)
                 if abs(p0[2] - p[2]) < 1e-9 and abs(np.linalg.norm(p0[:2]) - np.linalg.norm(p[:2])) < 1e-9
                 and abs(np.linalg.norm(v0) - np.linalg.norm(v)) < 1e-6 and abs(np.linalg.norm(w0) - np.linalg.norm(w)) < 1e-6]
        assert match


def test_height_jitter_scales_the_start_height_and_leaves_other_datasets_unchanged(templates):
    kw = dict(frame_rate=FRAME_RATE, gravity=GRAVITY, random_orientation=0.0, speed_jitter=0.0)
    plain = engine_tosses(templates, "pybullet", PUBLISHED, 8, seed=0, **kw)
    none = engine_tosses(templates, "pybullet", PUBLISHED, 8, seed=0, height_jitter=0.0, **kw)
    assert all(np.array_equal(a.positions, b.positions) for a, b in zip(plain, none))
    jittered = engine_tosses(templates, "pybullet", PUBLISHED, 8, seed=0, height_jitter=0.3, **kw)
    starts = [initial_state(t, FRAME_RATE, GRAVITY) for t in templates]
    ratios = []
    for s in jittered:
        p, _, v, _ = initial_state(s, FRAME_RATE, GRAVITY)
        # its template: the one of the same speed (no speed jitter)
        p0 = next(p0 for p0, _, v0, _ in starts if abs(np.linalg.norm(v0) - np.linalg.norm(v)) < 1e-6)
        raised = abs(lowest_corner_height(s)[:HISTORY].min() - 0.05 * 0.5 * float(s.scale[0])) < 1e-6
        ratios.append(p[2] / p0[2])
        assert 0.7 - 1e-9 <= ratios[-1] <= 1.3 + 1e-9 or raised
    assert max(abs(r - 1) for r in ratios) > 0.02


def test_bad_arguments(templates):
    with pytest.raises(ValueError):
        engine_tosses(templates, "pybullet", PUBLISHED, 0, 0, FRAME_RATE, GRAVITY)
    with pytest.raises(ValueError, match="unknown baseline engine"):
        engine_tosses(templates, "bullet3", PUBLISHED, 1, 0, FRAME_RATE, GRAVITY)


def test_fine_tuning_starts_from_the_other_runs_weights(tmp_path):
    from gns_fixtures import write_toss_dataset
    from gns.checkpoint import CheckpointError, read_checkpoint
    from gns.train import train
    from test_gns_train import quiet, tiny
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "pre", tiny("train.steps=5", "valid.every=0", "features.normalizer_steps=2"), log=quiet)
    pre = read_checkpoint(tmp_path / "pre" / "latest.pt")
    # one step at a vanishing learning rate: the new run holds the weights it started from (not
    # its own initialisation), normalisers exactly (their accumulation budget is spent)
    start = f"train.init_from={tmp_path / 'pre'}"
    small = ("train.steps=1", "valid.every=0", "train.lr_init=1e-12", "train.lr_final=0", "features.normalizer_steps=2")
    train(data, tmp_path / "ft0", tiny(*small, start), log=quiet)
    train(data, tmp_path / "fresh", tiny(*small), log=quiet)
    ft0 = read_checkpoint(tmp_path / "ft0" / "latest.pt")["model"]
    fresh = read_checkpoint(tmp_path / "fresh" / "latest.pt")["model"]
    for k, v in pre["model"].items():
        if "normalizer" in k:
            assert torch.equal(v, ft0[k]), k
        elif v.is_floating_point():
            assert torch.allclose(v, ft0[k], atol=1e-9), k
    assert any(not torch.allclose(v, fresh[k]) for k, v in pre["model"].items() if v.is_floating_point())
    # and a run of other features is refused in one line, naming the source
    with pytest.raises(CheckpointError, match="init_from"):
        train(data, tmp_path / "ft1", tiny("train.steps=1", "valid.every=0", "model.latent_size=8",
                                           "features.normalizer_steps=2",
                                           f"train.init_from={tmp_path / 'pre'}"), log=quiet)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        train(data, tmp_path / "ft2", tiny("train.steps=1", "valid.every=0", f"train.init_from={tmp_path / 'nope.pt'}"),
              log=quiet)
