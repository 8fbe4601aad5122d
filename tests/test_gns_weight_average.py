"""train.ema_decay: the moving average of the weights a run saves for use, and training on from its own."""
import pytest
import torch
from gns_fixtures import write_toss_dataset

from gns.checkpoint import TRAINED, load_model
from gns.zoo import export_model
from gns.config import ConfigError, build_config
from gns.checkpoint import read_checkpoint
from gns.train import train
from gns.weight_average import WeightAverage, decay_at
from test_gns_train import TINY, metrics, quiet, tiny


def test_the_average_follows_the_warmup_formula_then_the_decay():
    layer = torch.nn.Linear(2, 1)
    start = layer.weight.detach().clone()
    avg = WeightAverage(layer, 0.5)
    expected = start.clone()
    for n, value in enumerate([1.0, 2.0, 3.0, 4.0]):
        with torch.no_grad():
            layer.weight.fill_(value)
        avg.update()
        d = min(0.5, (1 + n) / (10 + n))
        expected = d * expected + (1 - d) * value
        assert torch.allclose(avg.average[0], expected)
    assert decay_at(0.999, 0) == pytest.approx(0.1) and decay_at(0.999, 10**6) == 0.999
    # the module keeps its own weights; the state dict carries the average, buffers untouched
    assert torch.all(layer.weight == 4.0)
    assert torch.allclose(avg.state_dict(layer)["weight"], expected)


def test_swapping_in_the_average_is_undone_after_the_block():
    layer = torch.nn.Linear(2, 1)
    avg = WeightAverage(layer, 0.9)
    own = layer.weight.detach().clone()
    with torch.no_grad():
        avg.average[0].add_(1.0)
    with avg.swapped_in():
        assert torch.allclose(layer.weight, own + 1.0)
    assert torch.equal(layer.weight, own)


@pytest.mark.parametrize("value", ["1", "-0.1", "1.5"])
def test_a_decay_outside_zero_one_is_a_one_line_error(value):
    with pytest.raises(ConfigError, match="train.ema_decay"):
        build_config(path=TINY, overrides=[f"train.ema_decay={value}"])


def test_a_run_saves_the_average_for_use_and_resumes_exactly(tmp_path):
    data = write_toss_dataset(tmp_path / "data", train=4, valid=1, frames=10)
    over = ("train.steps=12", "train.checkpoint_every=6", "valid.every=6", "train.ema_decay=0.9")
    train(data, tmp_path / "a", tiny(*over), log=quiet)
    train(data, tmp_path / "b", tiny(*over[1:], "train.steps=6"), log=quiet)
    train(data, tmp_path / "b", tiny(*over), resume=True, log=quiet)
    a, b = read_checkpoint(tmp_path / "a" / "latest.pt"), read_checkpoint(tmp_path / "b" / "latest.pt")
    for key in ("model", TRAINED):
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (key, k)
    assert metrics(tmp_path / "a")[-1]["loss"] == metrics(tmp_path / "b")[-1]["loss"]
    # the average differs from the trained weights, which are those of a run without it (same seed)
    train(data, tmp_path / "plain", tiny(*over[:3]), log=quiet)
    plain = read_checkpoint(tmp_path / "plain" / "latest.pt")
    weights = [k for k in plain["model"] if "network" in k and k.endswith("weight")]
    assert weights and all(torch.equal(a[TRAINED][k], plain["model"][k]) for k in plain["model"])
    assert any(not torch.equal(a["model"][k], a[TRAINED][k]) for k in weights)
    assert TRAINED not in plain
    # what evaluation and export use is the average
    sim, _ = load_model(tmp_path / "a" / "latest.pt")
    assert all(torch.equal(v, a["model"][k]) for k, v in sim.state_dict().items())
    slim = read_checkpoint(export_model(tmp_path / "a" / "latest.pt", tmp_path / "a.pt"))
    assert TRAINED not in slim and torch.equal(slim["model"][weights[0]], a["model"][weights[0]])
