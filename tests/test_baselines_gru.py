"""baselines.gru: a tiny GRU trains, rolls out with the right shapes, and learns free fall."""
import json
import os
import signal

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from baselines import gru
from baselines.toss import toss_errors
from datagen.shards import continuous, wxyz
from datagen.scenes import get_shape
from datagen.shards import Dataset, Scene, write_metadata, write_shard

G, RATE = 187.2, 148.0


def free_fall(rng, T=40) -> Scene:
    """A cube thrown high above the table: a parabola and a constant spin, exactly."""
    t = np.arange(T) / RATE
    p0, v0, w = rng.normal([0, 0, 30], [3, 3, 1]), rng.normal([0, 0, 5], [8, 8, 3]), rng.normal(0, 3, 3)
    acc = np.array([0.0, 0.0, -G])
    q0 = Rotation.random(random_state=rng)
    pos = p0 + v0 * t[:, None] + 0.5 * acc * t[:, None] ** 2
    quat = continuous(wxyz((Rotation.from_rotvec(w * t[:, None]) * q0).as_quat()))
    return Scene(positions=pos[:, None], quaternions=quat[:, None], velocities=(v0 + acc * t[:, None])[:, None],
                 angular_velocities=np.tile(w, (T, 1))[:, None], shape=["cube"], material=["m"],
                 scale=np.array([2.0]), mass=np.array([0.37]), friction=np.array([0.18]),
                 restitution=np.array([0.0]), attrs={"scene_id": 0})


def dataset(path, scenes, split="train"):
    path.mkdir()
    cube = get_shape("cube")
    write_shard(path / f"{split}-00000.h5", scenes, {"cube": (cube.vertices, cube.faces)})
    write_metadata(path, {"frame_rate": RATE, "gravity": [0, 0, -G], "floor": {"z": 0.0}, "materials_vary": False,
                          "splits": {split: {"num_scenes": len(scenes), "shards": [f"{split}-00000.h5"]}}})
    return path


def test_a_tiny_gru_trains_its_loss_falls_and_its_rollout_has_the_right_shapes(tmp_path):
    rng = np.random.default_rng(0)
    data = dataset(tmp_path / "d", [free_fall(rng) for _ in range(8)])
    cfg = gru.GRUConfig(hidden=16, layers=1, stride=4, steps=80, batch_size=8, log_every=10, lr_init=3e-3,
                        lr_decay_steps=1000)
    gru.train(data, tmp_path / "run", cfg)
    losses = [json.loads(line)["loss"] for line in (tmp_path / "run" / gru.METRICS).read_text().splitlines()]
    assert losses[-1] < 0.5 * losses[0]
    assert gru.trained(tmp_path / "run", cfg) and not gru.trained(tmp_path / "run", gru.GRUConfig())
    model, _ = gru.load(tmp_path / "run")
    sc = free_fall(rng, T=39)
    pred, truth = gru.rollout_scene(model, sc, stride=4)
    assert pred.positions.shape == (37, 1, 3) and pred.quaternions.shape == (37, 1, 4)   # frames 0..36: 10 steps of 4
    assert truth.num_frames == 37 and np.allclose(np.linalg.norm(pred.quaternions, axis=-1), 1.0)
    np.testing.assert_allclose(pred.positions[[0, 4, 8], 0], sc.positions[[0, 4, 8], 0])     # the 3 given states


def test_a_gru_stopped_by_sigterm_goes_on_exactly_where_it_stopped(tmp_path):
    rng = np.random.default_rng(2)
    data = dataset(tmp_path / "d", [free_fall(rng) for _ in range(8)])
    cfg = gru.GRUConfig(hidden=8, layers=1, stride=4, steps=40, batch_size=4, log_every=2, lr_decay_steps=40)
    gru.train(data, tmp_path / "straight", cfg)

    def stop_at_step_20(line):          # called every 10 log lines: steps 20 and 40
        if "step 20/" in line:
            os.kill(os.getpid(), signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM: GRU stopped at step 20 of 40"):
        gru.train(data, tmp_path / "split", cfg, log=stop_at_step_20)
    assert (tmp_path / "split" / gru.PARTIAL).exists() and not gru.trained(tmp_path / "split", cfg)
    gru.train(data, tmp_path / "split", cfg)
    a, b = gru.load(tmp_path / "straight")[1], gru.load(tmp_path / "split")[1]
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])
    losses = [[json.loads(line)["loss"] for line in (tmp_path / run / gru.METRICS).read_text().splitlines()]
              for run in ("straight", "split")]
    assert losses[0] == losses[1] and len(losses[0]) == 20
    assert not (tmp_path / "split" / gru.PARTIAL).exists()


def test_free_fall_is_predicted_after_training_on_free_fall(tmp_path):
    rng = np.random.default_rng(1)
    data = dataset(tmp_path / "d", [free_fall(rng) for _ in range(32)])
    test = dataset(tmp_path / "t", [free_fall(rng) for _ in range(4)], split="test")
    cfg = gru.GRUConfig(hidden=32, layers=1, stride=8, steps=300, batch_size=16, lr_init=3e-3, lr_decay_steps=300,
                        noise_std=0.0)
    gru.train(data, tmp_path / "run", cfg)
    r = gru.evaluate(tmp_path / "run", test)
    # a model that never moves the cube after its last given state scores, on the same tosses:
    frozen = []
    for sc in Dataset(test).load("test"):
        still = Scene(*(np.where(np.arange(sc.num_frames)[:, None, None] > 16, a[16], a) for a in
                        (sc.positions, sc.quaternions, sc.velocities, sc.angular_velocities)),
                      sc.shape, sc.material, sc.scale, sc.mass, sc.friction, sc.restitution, {})
        frozen.append(toss_errors(still, sc))
    still_pos, still_rot = np.mean(frozen, axis=0)
    assert r["num_scenes"] == 4 and r["penetration_pct"] == 0.0
    assert r["position_error_pct"] < 0.2 * still_pos
    assert r["rotation_error_deg"] < still_rot   # turning, if less well: a quaternion update is a product of two inputs
