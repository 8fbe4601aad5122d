"""Training: learning at all, checkpoints, exact resume, validation entries in metrics.jsonl."""
import json
from pathlib import Path

import pytest
import torch
from gns_fixtures import write_toss_dataset

from datagen.shards import Dataset
from gns.config import build_config
from gns.data import ObjectTracks
from gns.graph import MeshLibrary
from gns.checkpoint import load_model, read_checkpoint
from gns.train import learning_rate
from gns.train import train

TINY = Path(__file__).resolve().parents[1] / "configs" / "gns_tiny.toml"


def tiny(*overrides):
    return build_config(path=TINY, overrides=list(overrides))


def quiet(_):
    pass


def metrics(run):
    return [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_toss_dataset(tmp_path_factory.mktemp("toss"), train=6, valid=2, frames=10)


def test_tiny_model_overfits_a_handful_of_windows(tmp_path):
    few = write_toss_dataset(tmp_path / "few", train=2, valid=0, frames=5)   # 4 windows
    cfg = tiny("train.steps=150", "train.lr_init=0.003", "augment.rotate=false", "augment.noise_std=0",
               "model.latent_size=32", "model.hidden_size=32", "valid.every=0", "train.checkpoint_every=150")
    train(few, tmp_path / "run", cfg, log=quiet)
    losses = [m["loss"] for m in metrics(tmp_path / "run")]
    assert losses[-1] < losses[0] / 10, losses


def test_metrics_and_checkpoints_of_a_run(data, tmp_path):
    cfg = tiny("train.steps=20", "train.log_every=5", "train.checkpoint_every=5", "train.keep_checkpoints=2",
               "valid.every=10")
    assert train(data, tmp_path, cfg, log=quiet) == 20
    rows = metrics(tmp_path)
    assert [r["step"] for r in rows] == [5, 10, 15, 20]
    assert all({"step", "loss", "lr", "steps_per_sec"} <= r.keys() for r in rows)
    assert rows[1]["lr"] == pytest.approx(learning_rate(cfg, 9))
    valid = [r for r in rows if "valid_loss" in r]
    assert [r["step"] for r in valid] == [10, 20]
    assert all(r["valid_rollout_steps"] == 5 and r["valid_rollout_position_error"] > 0 for r in valid)
    assert sorted(p.name for p in tmp_path.glob("*.pt")) == ["ckpt-000015.pt", "ckpt-000020.pt", "latest.pt"]
    ckpt = read_checkpoint(tmp_path / "latest.pt")
    assert ckpt["step"] == 20 and ckpt["config"]["model"]["latent_size"] == 16
    assert set(ckpt["rng"]) == {"torch", "numpy", "python"} and ckpt["seed"] == 0
    assert ckpt["spec"]["node_features"] == ["velocity", "floor", "rest_position"]
    assert ckpt["spec"]["ranges"]["scale"][0] >= 0.7
    assert not list(tmp_path.glob("*.tmp"))


def test_load_model_rebuilds_the_trained_simulator(data, tmp_path):
    train(data, tmp_path, tiny("train.steps=10", "valid.every=0"), log=quiet)
    sim, cfg = load_model(tmp_path / "latest.pt")
    assert not sim.training and cfg.model.latent_size == 16
    assert float(sim.target_normalizer.count) > 0
    ckpt = torch.load(tmp_path / "latest.pt", weights_only=True)
    assert all(torch.equal(v, ckpt["model"][k]) for k, v in sim.state_dict().items())
    dataset = Dataset(data)
    batch = ObjectTracks(dataset.load("valid"), MeshLibrary(dataset.meshes)).batch(torch.arange(4))
    again, _ = load_model(tmp_path / "latest.pt")
    with torch.no_grad():
        a = sim.predict_next(*batch.history.unbind(1), batch.graph)
        b = again.predict_next(*batch.history.unbind(1), batch.graph)
    assert torch.equal(a, b) and torch.isfinite(a).all()


def test_resume_continues_exactly(data, tmp_path):
    common = ("train.checkpoint_every=3", "train.log_every=2", "valid.every=4")
    train(data, tmp_path / "straight", tiny("train.steps=12", *common), log=quiet)
    train(data, tmp_path / "split", tiny("train.steps=6", *common), log=quiet)
    train(data, tmp_path / "split", tiny("train.steps=12", *common), resume=True, log=quiet)
    a = read_checkpoint(tmp_path / "straight" / "latest.pt")
    b = read_checkpoint(tmp_path / "split" / "latest.pt")
    assert a["step"] == b["step"] == 12
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    state_a, state_b = a["optimizer"]["state"], b["optimizer"]["state"]
    assert all(torch.equal(state_a[i]["exp_avg_sq"], state_b[i]["exp_avg_sq"]) for i in state_a)
    assert a["rng"]["numpy"] == b["rng"]["numpy"]
    losses_a = {r["step"]: r["loss"] for r in metrics(tmp_path / "straight")}
    losses_b = {r["step"]: r["loss"] for r in metrics(tmp_path / "split")}
    assert losses_a[12] == losses_b[12] and losses_a[8] == losses_b[8]


def test_a_resumed_run_records_the_seconds_of_all_its_segments(data, tmp_path):
    common = ("train.checkpoint_every=4", "valid.every=0")
    train(data, tmp_path, tiny("train.steps=4", *common), log=quiet)
    first = read_checkpoint(tmp_path / "latest.pt")
    assert 0 < first["train_seconds"] < 600
    first["train_seconds"] = 1000.0      # as if the first segment had taken 1000 s
    torch.save(first, tmp_path / "latest.pt")
    train(data, tmp_path, tiny("train.steps=8", *common), resume=True, log=quiet)
    assert 1000 < read_checkpoint(tmp_path / "latest.pt")["train_seconds"] < 1600


def test_learning_rate_decays_from_init_to_final():
    cfg = build_config(overrides=["train.lr_init=1e-4", "train.lr_final=1e-6", "train.lr_decay_steps=100"])
    assert learning_rate(cfg, 0) == pytest.approx(1e-4)
    assert learning_rate(cfg, 100) == pytest.approx(1e-6 + 0.1 * (1e-4 - 1e-6))
    assert learning_rate(cfg, 10_000) == pytest.approx(1e-6)


def test_resume_after_a_crash_forgets_metrics_of_lost_steps(data, tmp_path):
    train(data, tmp_path, tiny("train.steps=8", "train.log_every=2", "train.checkpoint_every=4",
                               "train.keep_checkpoints=0", "valid.every=0"), log=quiet)
    # A crash after step 6 would leave latest.pt at step 4 and log lines for steps 6 and 8.
    (tmp_path / "latest.pt").write_bytes((tmp_path / "ckpt-000004.pt").read_bytes())
    (tmp_path / "ckpt-000008.pt").unlink()
    train(data, tmp_path, tiny("train.steps=8", "train.log_every=2", "train.checkpoint_every=4",
                               "valid.every=0"), resume=True, log=quiet)
    assert [r["step"] for r in metrics(tmp_path)] == [2, 4, 6, 8]


def test_resume_skips_a_damaged_latest_and_keeps_every_checkpoint(data, tmp_path, capsys):
    from pipelines.common import trained_step
    run = tmp_path / "run"
    train(data, run, tiny("train.steps=10", "train.checkpoint_every=5", "train.keep_checkpoints=0"), log=quiet)
    (run / "latest.pt").write_bytes(b"not a checkpoint")            # a crash while latest.pt was copied
    assert trained_step(run) == 10                                   # the pipelines resume, not restart
    lines = []
    train(data, run, tiny("train.steps=15", "train.checkpoint_every=5", "train.keep_checkpoints=0"),
          resume=True, log=lines.append)
    assert any("unreadable" in line and "ckpt-000010.pt" in line for line in lines), lines
    assert [p.name for p in sorted(run.glob("ckpt-*.pt"))] == ["ckpt-000005.pt", "ckpt-000010.pt", "ckpt-000015.pt"]
    assert read_checkpoint(run / "latest.pt")["step"] == 15


def test_resume_tolerates_a_torn_metrics_line(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, tiny("train.steps=10", "train.checkpoint_every=5", "train.log_every=5"), log=quiet)
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"step": 11, "loss": 0.')                         # cut mid-write by a crash
    said = []
    train(data, run, tiny("train.steps=15", "train.checkpoint_every=5", "train.log_every=5"), resume=True,
          log=said.append)
    assert [m["step"] for m in metrics(run)] == [5, 10, 15]
    assert any("dropped 1 unreadable line" in line for line in said), said


def test_an_exported_model_cannot_be_resumed_but_says_why(data, tmp_path):
    from gns.checkpoint import CheckpointError
    from gns.zoo import export_model
    run = tmp_path / "run"
    train(data, run, tiny("train.steps=5", "train.checkpoint_every=5"), log=quiet)
    export_model(run / "latest.pt", tmp_path / "exported" / "latest.pt")
    with pytest.raises(CheckpointError, match="exported model"):
        train(data, tmp_path / "exported", tiny("train.steps=10"), resume=True, log=quiet)


def test_a_cuda_device_on_a_cpu_build_is_one_line(data, tmp_path):
    from gns.config import ConfigError
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the error cannot happen here")
    with pytest.raises(ConfigError, match="CUDA is not available"):
        train(data, tmp_path / "run", tiny("train.device=cuda", "train.steps=2"), log=quiet)
    assert not (tmp_path / "run").exists()


def test_a_signal_stops_training_after_the_step_with_a_checkpoint_there(data, tmp_path):
    import os
    import signal
    import threading
    import time

    from gns.train import TrainingInterrupted
    cfg = tiny("train.steps=100000", "train.checkpoint_every=100000", "valid.every=0", "train.log_every=1")
    # SIGTERM (a cluster's preemption, `kill`) once steps are logged; the default would lose every step
    done = threading.Event()

    def send():
        log = tmp_path / "metrics.jsonl"
        while not done.is_set():
            if log.exists() and len(log.read_text().splitlines()) >= 3:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.05)
    before = signal.getsignal(signal.SIGTERM)   # another test's library (ray) may have set its own
    sender = threading.Thread(target=send)
    sender.start()
    try:
        with pytest.raises(TrainingInterrupted, match="SIGTERM: stopped at step"):
            train(data, tmp_path, cfg, log=quiet)
    finally:
        done.set()
        sender.join()
    ckpt = read_checkpoint(tmp_path / "latest.pt")
    assert 0 < ckpt["step"] < 100000 and metrics(tmp_path)[-1]["step"] == ckpt["step"]
    assert signal.getsignal(signal.SIGTERM) is before                   # handlers given back
    # and it goes on from there, as a resumed run does
    train(data, tmp_path, tiny("train.steps=" + str(ckpt["step"] + 2), "train.checkpoint_every=100000",
                               "valid.every=0", "train.log_every=1"), resume=True, log=quiet)
    assert read_checkpoint(tmp_path / "latest.pt")["step"] == ckpt["step"] + 2
