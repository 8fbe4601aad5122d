"""--device on train/eval/rollout, and bf16 autocast of the network (and of nothing else)."""
import json
from pathlib import Path

import pytest
import torch
from gns_fixtures import write_toss_dataset

from gns.cli import main
from gns.config import build_config
from gns.train import train

TINY = Path(__file__).resolve().parents[1] / "configs" / "gns_tiny.toml"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_toss_dataset(tmp_path_factory.mktemp("dev"), train=3, valid=1, frames=8)


def run_cli(args, capsys):
    try:
        code = main(args)
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr()


def test_device_flag_overrides_the_config(data, tmp_path, capsys):
    code, _ = run_cli(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--config", str(TINY),
                       "--steps", "2", "--set", "train.device=cuda:7", "valid.every=0", "--device", "cpu"], capsys)
    assert code is None
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["device"] == "cpu"
    code, out = run_cli(["eval", "--run", str(tmp_path / "run"), "--data", str(data), "--split", "valid",
                         "--device", "cpu", "--json", str(tmp_path / "e.json")], capsys)
    assert code is None and json.loads((tmp_path / "e.json").read_text())["device"] == "cpu"


@pytest.mark.parametrize("command", ["train", "eval", "rollout"])
def test_an_unusable_device_is_one_line(data, tmp_path, capsys, command):
    args = {"train": ["train", "--data", str(data), "--out", str(tmp_path / "r"), "--config", str(TINY)],
            "eval": ["eval", "--run", "real_cubes_16", "--data", str(data)],
            "rollout": ["rollout", "--run", "real_cubes_16", "--data", str(data), "--out", str(tmp_path / "o")]}
    code, out = run_cli(args[command] + ["--device", "warp-drive"], capsys)
    assert code == 2
    assert out.err.startswith("error: ") and "is not a torch device" in out.err and out.err.count("\n") == 1
    if not torch.cuda.is_available():
        code, out = run_cli(args[command] + ["--device", "cuda"], capsys)
        assert code == 2 and "CUDA is not available" in out.err and out.err.count("\n") == 1


def test_bf16_autocast_runs_the_network_only_and_still_learns(data, tmp_path):
    seen = {}

    def spy(module, inputs, output):
        seen.setdefault(type(module).__name__, set()).add(output.dtype)

    cfg = build_config(path=TINY, overrides=["train.steps=120", "train.autocast=bf16", "augment.rotate=false",
                                             "augment.noise_std=0", "valid.every=0", "train.lr_init=0.003",
                                             "train.log_every=10", "train.checkpoint_every=120"])
    import gns.train as gt
    original = gt.build_simulator

    def build(cfg_, spec):
        sim = original(cfg_, spec)
        for m in sim.modules():
            if isinstance(m, (torch.nn.Linear,)):
                m.register_forward_hook(spy)
        sim.target_normalizer.register_forward_hook(spy)
        build.sim = sim
        return sim

    gt.build_simulator = build
    try:
        train(data, tmp_path / "run", cfg, log=lambda _: None)
    finally:
        gt.build_simulator = original
    assert seen["Linear"] == {torch.bfloat16}                 # every layer of the network in bf16
    assert seen["Normalizer"] == {torch.float32}              # normalisers outside autocast
    sim = build.sim
    assert all(p.dtype == torch.float32 for p in sim.parameters())   # weights stay float32
    assert sim.target_normalizer.sum.dtype == torch.float64
    losses = [json.loads(line)["loss"] for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert losses[-1] < losses[0] / 3, losses
