"""What a run records besides its checkpoints: provenance (versions, commit, the data's
fingerprint) in the run, its checkpoints and eval/rollout outputs; TensorBoard event files
(`--tensorboard`); training-curve plots (`gns plot-curves`)."""
import json
import sys
from pathlib import Path

import pytest
from gns_fixtures import write_toss_dataset

from datagen.shards import Dataset
from gns.cli import main
from gns.checkpoint import read_checkpoint
from gns.run_folder import TENSORBOARD_DIR, read_metrics

TINY = str(Path(__file__).resolve().parents[1] / "configs" / "gns_tiny.toml")
LIBRARIES = ("python", "torch", "numpy", "pybullet", "h5py", "trimesh", "scipy")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_toss_dataset(tmp_path_factory.mktemp("toss"), train=4, valid=2, frames=8)


@pytest.fixture(scope="module")
def tb_run(data, tmp_path_factory):
    """6 steps with TensorBoard on, validating at 3 and 6; then resumed to 9."""
    run = tmp_path_factory.mktemp("run") / "r"
    train(data, run, "--steps", 6, "--tensorboard", "--set", "train.log_every=3", "valid.every=3")
    train(data, run, "--steps", 9, "--resume")
    return run


def train(data, run, *args):
    main(["train", "--data", str(data), "--out", str(run), "--config", TINY, *map(str, args)])


def one_error(capsys, argv) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(list(map(str, argv)))
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    acc = EventAccumulator(str(run / TENSORBOARD_DIR))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_tensorboard_holds_the_metrics_of_every_logged_step(tb_run):
    # tensorboard is in the dev extra, so this runs wherever the README's test command ran
    logged = read_metrics(tb_run / "metrics.jsonl")
    assert [e["step"] for e in logged] == [3, 6, 9]
    got = scalars(tb_run)
    assert {"train/loss", "train/lr", "valid/loss", "valid/rollout_position_error", "speed/steps_per_sec"} <= set(got)
    for key, tag in (("loss", "train/loss"), ("lr", "train/lr"), ("valid_loss", "valid/loss")):
        want = [(e["step"], e[key]) for e in logged if key in e]
        assert [s for s, _ in got[tag]] == [s for s, _ in want]            # resumed: no step twice
        assert [v for _, v in got[tag]] == pytest.approx([v for _, v in want], rel=1e-6)
    assert [s for s, _ in got["train/loss"]] == [3, 6, 9] and [s for s, _ in got["valid/loss"]] == [3, 6]


def test_without_tensorboard_installed_it_is_one_line_and_nothing_written(data, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboard", None)      # as if the extra were not installed
    run = tmp_path / "r"
    line = one_error(capsys, ["train", "--data", data, "--out", run, "--config", TINY, "--steps", 2, "--tensorboard"])
    assert "needs TensorBoard" in line and "rigid-gns[tensorboard]" in line
    assert not run.exists()


def test_run_and_checkpoints_record_versions_commit_and_data_fingerprint(tb_run, data):
    fingerprint = Dataset(data).fingerprint
    prov = json.loads((tb_run / "provenance.json").read_text())
    assert prov["data"] == {"path": str(data), "fingerprint": fingerprint}
    assert all(prov["versions"][k] for k in LIBRARIES)
    assert prov["start_step"] == 6 and prov["earlier"][0]["start_step"] == 0    # the resume is a second run of the training
    assert prov["earlier"][0]["data"]["fingerprint"] == fingerprint
    ckpt = read_checkpoint(tb_run / "latest.pt")
    assert ckpt["provenance"] == prov
    assert "commit" in (prov["code"] or {"commit": None})


def test_eval_json_and_rollouts_name_the_data_and_the_training_data(tb_run, data, tmp_path, capsys):
    main(["eval", "--run", str(tb_run), "--data", str(data), "--split", "valid", "--json", str(tmp_path / "e.json")])
    result = json.loads((tmp_path / "e.json").read_text())
    fingerprint = Dataset(data).fingerprint
    assert result["data_fingerprint"] == result["trained_on_fingerprint"] == fingerprint
    assert all(result["provenance"]["versions"][k] for k in LIBRARIES)
    out = tmp_path / "roll"
    main(["rollout", "--run", str(tb_run), "--data", str(data), "--split", "valid", "--out", str(out)])
    rolled = Dataset(out).meta
    assert rolled["rollout"]["trained_on_fingerprint"] == fingerprint
    assert rolled["fingerprint"] != fingerprint and rolled["fingerprint"] == Dataset(out).fingerprint
    # an exported model keeps what it was trained on
    main(["export", "--run", str(tb_run), "--out", str(tmp_path / "m.pt")])
    assert read_checkpoint(tmp_path / "m.pt")["provenance"]["data"]["fingerprint"] == fingerprint


def test_overwrite_removes_the_old_event_files(data, tmp_path):
    run = tmp_path / "r"
    train(data, run, "--steps", 2, "--tensorboard")
    train(data, run, "--steps", 2, "--overwrite")
    assert not list((run / TENSORBOARD_DIR).glob("events.out.tfevents.*"))
    assert json.loads((run / "provenance.json").read_text())["start_step"] == 0


def test_plot_curves_of_two_runs(tb_run, data, tmp_path, capsys):
    other = tmp_path / "other"
    train(data, other, "--steps", 4, "--set", "train.log_every=1", "valid.every=0")
    out = tmp_path / "plots" / "curves.png"
    main(["plot-curves", str(tb_run), str(other / "metrics.jsonl"), "--out", str(out)])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert "wrote" in capsys.readouterr().out
    assert not [p for p in out.parent.iterdir() if p.name != "curves.png"]      # no temporary file left


@pytest.mark.parametrize("case, words", [
    ("no_run", "not a training run folder"),
    ("empty", "holds no metrics"),
    ("bad_suffix", ".png, .pdf or .svg"),
])
def test_plot_curves_bad_input_is_one_line(tmp_path, capsys, case, words):
    run = tmp_path / "run"
    run.mkdir()
    out = tmp_path / ("c.txt" if case == "bad_suffix" else "c.png")
    if case == "empty":
        (run / "metrics.jsonl").write_text('{"step": 1, "los')        # torn by a crash
    target = tmp_path / "missing" if case == "no_run" else run
    assert words in one_error(capsys, ["plot-curves", target, "--out", out])
    assert not out.exists()


def test_a_resume_after_a_crash_does_not_log_a_step_twice(data, tmp_path):
    run = tmp_path / "r"
    train(data, run, "--steps", 6, "--tensorboard", "--set", "train.log_every=3", "train.checkpoint_every=3")
    for name in ("latest.pt", "ckpt-000006.pt"):    # crashed after logging step 6, before its checkpoint
        (run / name).unlink()
    train(data, run, "--steps", 6, "--resume", "--set", "train.log_every=3", "train.checkpoint_every=3")
    assert [s for s, _ in scalars(run)["train/loss"]] == [3, 6]
    assert [e["step"] for e in read_metrics(run / "metrics.jsonl")] == [3, 6]
