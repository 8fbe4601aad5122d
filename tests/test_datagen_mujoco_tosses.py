"""datagen toss --engine mujoco: reproducible real-cube-like tosses at three contact stiffnesses."""
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")  # the [mujoco] extra; the dev extra installs it

from datagen import mujoco_tosses as mt  # noqa: E402
from datagen.cli import main  # noqa: E402
from datagen.contactnets import read_experiment, read_toss, toss_to_scene  # noqa: E402
from datagen.inspect import inspect  # noqa: E402
from datagen.shards import Dataset  # noqa: E402

SRC = Path(__file__).parent / "data" / "contactnets"


def toss(tmp_path, level, *extra, name=None):
    out = tmp_path / (name or level)
    assert main(["toss", "--engine", "mujoco", "--stiffness", level, "--seed", "3", "--out", str(out), "--quiet",
                 *extra]) == 0
    return Dataset(out)


def test_same_seed_same_tosses_nested_and_the_same_starts_at_every_level(tmp_path):
    a = toss(tmp_path, "hard", "--scenes", "3", "--test", "1", "--frames", "30")
    b = toss(tmp_path, "hard", "--scenes", "3", "--test", "1", "--frames", "30", "--workers", "2", name="again")
    assert a.fingerprint == b.fingerprint                                  # any number of workers
    sharded = mt.generate_tosses(mt.load_config(None, ["scene.frames=30"], "hard"), 3, {"train": 3},
                                 tmp_path / "sharded", per_shard=1, workers=2)
    assert len(sharded["splits"]["train"]["shards"]) == 3
    for x, y in zip(Dataset(tmp_path / "sharded").load("train"), a.load("train")):
        np.testing.assert_array_equal(x.positions, y.positions)           # shards in order
    small = toss(tmp_path, "hard", "--scenes", "2", "--frames", "30", name="small")
    for x, y in zip(small.load("train"), a.load("train")):
        np.testing.assert_array_equal(x.positions, y.positions)
    soft = toss(tmp_path, "soft", "--scenes", "3", "--frames", "30")
    for x, y in zip(soft.load("train"), a.load("train")):
        np.testing.assert_array_equal(x.positions[0], y.positions[0])     # one start, two stiffnesses
        np.testing.assert_array_equal(x.quaternions[0], y.quaternions[0])
    assert a.load("test")[0].positions[0, 0, 0] != a.load("train")[0].positions[0, 0, 0]   # held out: other draws
    meta = a.meta
    assert meta["config"]["contact"]["timeconst"] == 0.02 and soft.meta["config"]["contact"]["timeconst"] == 0.1
    assert meta["frame_rate"] == 148.0 and meta["num_frames"] == 30 and meta["engine"]["name"] == "mujoco"
    assert inspect(soft.root)[0] == []      # sinking in is soft contact, not a problem


def test_softer_contact_sinks_deeper_and_flight_before_contact_is_ballistic(tmp_path):
    pen = {}
    for level in ("hard", "medium", "soft"):
        ds = toss(tmp_path, level, "--scenes", "3", "--frames", "60")
        scenes = ds.load("train")
        pen[level] = mt.dataset_penetration(scenes)
        sc = scenes[0]
        g, dt = -ds.gravity[2], 1.0 / ds.frame_rate
        t = np.arange(3) * dt      # the start is >= 0.9 half-widths up: no contact in the first 3 frames
        z = sc.positions[0, 0, 2] + sc.velocities[0, 0, 2] * t - 0.5 * g * t ** 2
        np.testing.assert_allclose(sc.positions[:3, 0, 2], z, atol=2e-3)
        assert sc.positions[-1, 0, 2] < 1.1      # landed by 0.4 s
    assert pen["hard"]["mean_pct"] < pen["medium"]["mean_pct"] < pen["soft"]["mean_pct"]
    assert pen["hard"]["max_pct"] < pen["medium"]["max_pct"] < pen["soft"]["max_pct"]


def test_starts_follow_the_fitted_distribution_and_the_fit_reads_real_tosses():
    cfg = mt.load_config()
    starts = [mt.sample_start(cfg, np.random.default_rng([0, 0, i])) for i in range(400)]
    speed = [np.linalg.norm(v[:2]) for _, _, v, _ in starts]
    assert abs(np.mean(speed) - cfg["start"]["speed_mean"]) < 0.5
    assert all(np.isclose(np.linalg.norm(q), 1.0) for _, q, _, _ in starts)
    consts = read_experiment(SRC)
    real = [toss_to_scene(read_toss(SRC / "tosses_processed" / f"{i}.pt"), i, "", consts) for i in (55, 229, 274)]
    fit = mt.fit_starts(real, 1.0 / consts["dt"], consts["g"])
    assert fit["num_tosses"] == 3 and len(fit["position_mean"]) == 3
    assert 15 < fit["speed_mean"] < 30 and 1.5 < fit["position_mean"][2] < 4    # real tosses: ~22 hw/s, ~2.7 hw up


def test_bad_input_is_one_error_line(tmp_path, capsys):
    out = str(tmp_path / "x")
    assert main(["toss", "--engine", "mujoco", "--stiffness", "squishy", "--out", out]) == 2
    assert main(["toss", "--engine", "mujoco", "--shapes", "cube", "--out", out]) == 2
    assert main(["toss", "--stiffness", "soft", "--out", out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("error: ") for line in err)
    assert "squishy" in err[0] and "--shapes" in err[1] and "--engine mujoco" in err[2]


@pytest.mark.skipif(os.name != "posix", reason="signals between processes")
def test_sigterm_stops_the_workers_and_leaves_no_shard(tmp_path):
    from datagen_helpers import sigterm_toss
    out = tmp_path / "tosses"
    status, err = sigterm_toss(out, "--engine", "mujoco", "--scenes", "20000", "--workers", "2", "--quiet",
                               "--scenes-per-shard", "50")
    assert status == 2
    assert err.strip().splitlines() == ["error: interrupted; its shards were removed (rerun the same command)"]
    assert not list(out.glob("*.h5")) and not (out / "metadata.json").exists()
