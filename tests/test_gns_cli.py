"""`gns train` end to end, and every bad input giving one `error:` line and a non-zero exit."""
import json
import math
from pathlib import Path

import pytest
import torch
from gns_fixtures import write_toss_dataset

from gns.cli import main
from gns.simulator import LearnedSimulator
from gns.checkpoint import read_checkpoint

TINY = str(Path(__file__).resolve().parents[1] / "configs" / "gns_tiny.toml")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return str(write_toss_dataset(tmp_path_factory.mktemp("toss"), train=4, valid=2, frames=8))


def run(*args):
    main(["train", *map(str, args)])


def fails(capsys, *args, code=2) -> str:
    """Run `gns train ARGS`, expect exit status `code` and exactly one stderr line; return it."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        run(*args)
    assert exc.value.code == code
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def test_train_then_resume_to_more_steps(data, tmp_path, capsys):
    run("--data", data, "--out", tmp_path, "--config", TINY, "--steps", 4, "--set", "valid.every=2")
    assert read_checkpoint(tmp_path / "latest.pt")["step"] == 4
    run("--data", data, "--out", tmp_path, "--steps", 6, "--resume")
    ckpt = read_checkpoint(tmp_path / "latest.pt")
    assert ckpt["step"] == 6
    # Resuming without --config keeps the checkpoint's config, not the defaults.
    assert ckpt["config"]["model"]["latent_size"] == 16 and ckpt["config"]["valid"]["every"] == 2
    steps = [json.loads(line)["step"] for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2, 4, 6]
    assert "done at step 6" in capsys.readouterr().out


def test_not_a_dataset(tmp_path, capsys):
    line = fails(capsys, "--data", tmp_path / "nothing", "--out", tmp_path / "run", "--config", TINY)
    assert "not a dataset folder" in line


def test_unknown_key_in_toml(data, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[model]\nlatnet_size = 8\n")
    line = fails(capsys, "--data", data, "--out", tmp_path / "run", "--config", bad)
    assert "'model.latnet_size'" in line and "did you mean 'model.latent_size'" in line


def test_unknown_key_in_set(data, tmp_path, capsys):
    line = fails(capsys, "--data", data, "--out", tmp_path / "run", "--config", TINY, "--set", "trian.steps=3")
    assert "'trian.steps'" in line and "did you mean 'train.steps'" in line


def test_wrong_value_type_in_set(data, tmp_path, capsys):
    line = fails(capsys, "--data", data, "--out", tmp_path / "run", "--config", TINY, "--set", "train.steps=many")
    assert "train.steps" in line and "a whole number" in line


def test_set_values_are_read_and_typed_as_datagen_reads_them(data, tmp_path, capsys):
    """One value parser and one typing rule for both tools: False is a boolean, 'no' is not."""
    from gns.config import build_config
    assert build_config(path=TINY, overrides=["augment.rotate=False"]).augment.rotate is False
    line = fails(capsys, "--data", data, "--out", tmp_path / "run", "--config", TINY, "--set", "augment.rotate=no")
    assert line == "error: config key 'augment.rotate' in --set must be true or false, got 'no'"


def test_missing_config_file(data, tmp_path, capsys):
    line = fails(capsys, "--data", data, "--out", tmp_path / "run", "--config", tmp_path / "nope.toml")
    assert "config file not found" in line


def test_refuses_to_overwrite_a_run_without_resume(data, tmp_path, capsys):
    run("--data", data, "--out", tmp_path, "--config", TINY, "--steps", 2)
    line = fails(capsys, "--data", data, "--out", tmp_path, "--config", TINY, "--steps", 2)
    assert "already holds checkpoints" in line and "--resume" in line
    run("--data", data, "--out", tmp_path, "--config", TINY, "--steps", 3, "--overwrite")
    assert sorted(p.name for p in tmp_path.glob("*.pt")) == ["ckpt-000003.pt", "latest.pt"]


def test_resume_without_checkpoint(data, tmp_path, capsys):
    line = fails(capsys, "--data", data, "--out", tmp_path, "--config", TINY, "--resume")
    assert "nothing to resume" in line


def test_resume_with_incompatible_config(data, tmp_path, capsys):
    run("--data", data, "--out", tmp_path, "--config", TINY, "--steps", 2)
    line = fails(capsys, "--data", data, "--out", tmp_path, "--steps", 4, "--resume",
                 "--set", "model.latent_size=32", "features.rest_edges=false")
    assert "model.latent_size is 16 in the checkpoint, 32 now" in line
    assert "features.rest_edges is True in the checkpoint, False now" in line


def test_resume_on_data_with_other_features(data, tmp_path, capsys):
    run("--data", data, "--out", tmp_path / "run", "--config", TINY, "--steps", 2)
    mixed = write_toss_dataset(tmp_path / "mixed", train=2, valid=0, frames=8, materials_vary=True)
    line = fails(capsys, "--data", mixed, "--out", tmp_path / "run", "--steps", 4, "--resume")
    assert "node_features" in line and "material" in line


def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(data, tmp_path, capsys, monkeypatch):
    real_loss = LearnedSimulator.loss
    calls = {"n": 0}

    def loss_that_breaks_at_step_3(self, *args):
        value = real_loss(self, *args)
        calls["n"] += 1 if self.training else 0
        return value * math.nan if self.training and calls["n"] == 3 else value

    monkeypatch.setattr(LearnedSimulator, "loss", loss_that_breaks_at_step_3)
    line = fails(capsys, "--data", data, "--out", tmp_path, "--config", TINY, "--steps", 10,
                 "--set", "train.checkpoint_every=1", code=1)
    assert "nan at step 3" in line and "ckpt-000002.pt" in line
    ckpt = read_checkpoint(tmp_path / "latest.pt")
    assert ckpt["step"] == 2
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())
    assert not (tmp_path / "ckpt-000003.pt").exists()


def test_help_lists_train():
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0


def test_all_node_features_off(data, tmp_path, capsys):
    line = fails(capsys, "--data", data, "--out", tmp_path, "--config", TINY, "--set", "features.velocity=false",
                 "features.floor_distance=false", "features.rest_position=false")
    assert "no node features" in line


def test_presets_resolve_by_name_and_a_missing_one_lists_them():
    from gns.config import ConfigError, build_config
    assert build_config(path="gns_cpu").model.latent_size == 64
    assert build_config(path="configs/gns_tiny.toml").model.latent_size == build_config(path="gns_tiny").model.latent_size
    with pytest.raises(ConfigError, match="presets: gns_cpu, gns_paper, gns_tiny, kubric_movi_a, movi_a"):
        build_config(path="gns_huge")


def test_eval_and_rollout_threads(data, tmp_path, capsys):
    run("--data", data, "--out", tmp_path / "r", "--config", TINY, "--steps", 2, "--set", "valid.every=0")
    for cmd in (["eval"], ["rollout", "--out", str(tmp_path / "roll")]):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            main([*cmd, "--run", str(tmp_path / "r"), "--data", data, "--split", "valid", "--threads", "0"])
        assert exc.value.code == 2
        assert capsys.readouterr().err.strip() == "error: --threads must be >= 1, got 0"
    main(["eval", "--run", str(tmp_path / "r"), "--data", data, "--split", "valid", "--threads", "2"])
    assert torch.get_num_threads() == 2
    main(["eval", "--run", str(tmp_path / "r"), "--data", data, "--split", "valid"])
    assert torch.get_num_threads() == 1


def test_a_reader_that_leaves_ends_the_command_quietly(monkeypatch, capfd):
    """`gns eval ... | head`: the closed pipe is no `error:` line, and the exit status says it failed."""
    import gns.cli as cli

    def leaves(args):
        raise BrokenPipeError(32, "Broken pipe")
    monkeypatch.setattr(cli, "cmd_eval", leaves)
    with pytest.raises(SystemExit) as stop:
        cli.main(["eval", "--run", "x", "--data", "y"])
    assert stop.value.code == cli.EXIT_FAILED
    assert "error" not in capfd.readouterr().err


@pytest.mark.parametrize("flags, line", [
    (["--batch", "0"], "error: --batch must be a whole number >= 1, got 0"),
    (["--batch", "-5"], "error: --batch must be a whole number >= 1, got -5"),
    (["--sleep", "--sleep-fraction", "-1"], "error: --sleep-fraction must be a finite number > 0, got -1"),
    (["--sleep", "--sleep-fraction", "0"], "error: --sleep-fraction must be a finite number > 0, got 0"),
    (["--sleep", "--sleep-fraction", "inf"], "error: --sleep-fraction must be a finite number > 0, got inf"),
    (["--sleep-fraction", "0.2"], "error: --sleep-fraction sets when an object is at rest: it needs --sleep"),
    (["--free-flight", "--free-clearance", "-1"], "error: --free-clearance must be a finite height >= 0 above the "
                                                  "floor, got -1"),
    (["--free-flight", "--free-clearance", "nan"], "error: --free-clearance must be a finite height >= 0 above the "
                                                   "floor, got nan"),
    (["--limit", "0"], "error: --limit must be >= 1 scene, got 0"),
])
@pytest.mark.parametrize("command", ["rollout", "eval"])
def test_out_of_range_rollout_flags_are_one_line_naming_the_flag(tmp_path, capsys, command, flags, line):
    out = ["--out", str(tmp_path / "roll")] if command == "rollout" else []
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main([command, "--run", "movi_a", "--data", str(tmp_path / "no_data"), *out, *flags])
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [line]    # before the data is even looked at
    assert not (tmp_path / "roll").exists()
