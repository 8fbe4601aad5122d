"""--autocast auto: bf16 only where it measures faster (gns.speedups)."""
import warnings

import pytest
import torch

from gns.config import ConfigError
from gns.speedups import MARGIN, bf16_speedup, resolve_autocast
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec
from test_gns_train import tiny


def test_named_choices_pass_through_and_auto_follows_the_measurement():
    assert resolve_autocast("none", 64) == "none" and resolve_autocast("bf16", 64, measure=lambda w, device: 1.8) == "bf16"
    assert resolve_autocast("auto", 64, measure=lambda w, device: 1.8) == "bf16"
    # a CPU where bf16 products are slower (an Intel Xeon's: 0.55x), or barely faster, keeps float32
    assert resolve_autocast("auto", 64, measure=lambda w, device: 0.55) == "none"
    assert resolve_autocast("auto", 64, measure=lambda w, device: MARGIN * 0.99) == "none"
    with pytest.raises(ValueError, match="autocast"):
        resolve_autocast("fp16", 64)


def test_bf16_by_name_is_kept_but_warns_in_one_line_where_the_cpu_emulates_it():
    # an AMD EPYC without avx512: a bf16 product 25x slower, rollouts 12x
    with pytest.warns(UserWarning, match="10x slower than float32 on this CPU") as caught:
        assert resolve_autocast("bf16", 64, measure=lambda w, device: 0.1) == "bf16"
    assert "\n" not in str(caught[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_autocast("bf16", 64, measure=lambda w, device: 1.8) == "bf16"
        assert resolve_autocast("bf16", 64, measure=lambda w, device: 0.55) == "bf16"   # slower, not emulated
        assert resolve_autocast("none", 64, measure=lambda w, device: 0.1) == "none"


def test_the_measurement_is_a_positive_ratio_taken_once():
    first = bf16_speedup(16, rows=256, repeats=2)
    assert first > 0 and bf16_speedup(16, rows=256, repeats=2) == first


def test_a_simulator_set_to_auto_measures_at_its_latent_width_and_says_what_it_took(monkeypatch):
    from gns import speedups
    cfg = tiny()
    sim = LearnedSimulator(cfg.model, cfg.features, ModelSpec(floor=None, materials_vary=False))
    asked = []
    monkeypatch.setattr(speedups, "resolve_autocast", lambda name, width, device: asked.append(width) or "bf16")
    sim.set_speed("auto")
    assert asked == [cfg.model.latent_size] and sim.autocast == torch.bfloat16 and sim.autocast_used == "bf16"
    sim.set_speed("none")
    assert sim.autocast is None and sim.autocast_used == "none"


def test_train_autocast_accepts_auto_and_names_the_choices_on_a_typo():
    assert tiny("train.autocast=auto").train.autocast == "auto"
    with pytest.raises(ConfigError, match="'none', 'bf16' or 'auto'"):
        tiny("train.autocast=bf32")


def test_the_cli_shows_a_warning_as_one_line_and_leaves_the_format_as_it_found_it(monkeypatch, capsys):
    from gns import cli

    def run(args):
        print(warnings.formatwarning("shown", UserWarning, "f.py", 1), end="")

    before = warnings.formatwarning
    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    monkeypatch.setattr(parser, "parse_args", lambda argv: type("A", (), {"run": staticmethod(run)})())
    cli.main([])
    assert capsys.readouterr().out == "warning: shown\n" and warnings.formatwarning is before


def test_compile_without_a_cpp_compiler_warns_and_runs_the_network_as_it_is(monkeypatch):
    import shutil
    from gns import speedups
    net = torch.nn.Linear(3, 2)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.delenv("CXX", raising=False)
    with pytest.warns(UserWarning, match="no C.. compiler"):
        assert speedups.compiled(net) is net
    monkeypatch.setattr(shutil, "which", lambda name: "/usr/bin/g++" if name == "g++" else None)
    assert speedups.compiled(net) is not net
