"""Issue 11 for gns and the pipelines: no input destroys data, every bad input gets one line.

Torn checkpoints and logs, outputs that overlap the input, diverging rollouts, outputs that
cannot be written, a missing GPU, an exported model given to resume, single-object models on
multi-object scenes (docs/reliability.md lists each case and its line).
"""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from gns_fixtures import write_toss_dataset

from datagen.shards import Dataset, Scene, write_metadata, write_shard
from gns.cli import main as gns_main
from gns.config import build_config
from gns.evaluate import evaluate_run
from gns.simulator import LearnedSimulator
from gns.checkpoint import read_checkpoint
from gns.train import train
from pipelines import movi_a
from pipelines.common import guarded, train_stage

TINY = Path(__file__).resolve().parents[1] / "configs" / "gns_tiny.toml"
STEPS = ["train.checkpoint_every=1", "train.keep_checkpoints=0", "valid.every=0", "train.log_every=1"]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A tiny dataset (4 valid scenes to roll out) and a run with ckpt-000001..4.pt."""
    root = tmp_path_factory.mktemp("rel")
    data = write_toss_dataset(root / "data", train=4, valid=4, frames=8)
    train(data, root / "run", build_config(path=TINY, overrides=["train.steps=4", *STEPS]), log=lambda s: None)
    return data, root / "run"


@pytest.fixture
def run(made, tmp_path):
    """A private copy of the trained run, free to damage."""
    return Path(shutil.copytree(made[1], tmp_path / "run"))


def one_error(capsys, argv, code=2) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        gns_main([str(a) for a in argv])
    assert e.value.code == code
    err = capsys.readouterr().err.strip().splitlines()
    # warnings and a progress bar may come first; the failure itself is one last line
    assert err[-1].startswith("error: ") and sum(line.startswith("error") for line in err) == 1, err
    assert not any("Traceback" in line for line in err), err
    return err[-1]


def tear(path: Path) -> None:
    """What a crash or a full disk mid-write leaves: the first bytes only."""
    path.write_bytes(path.read_bytes()[:1000])


def steps_logged(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]


# ---- 3. a torn latest.pt: resume from the newest readable checkpoint, delete nothing ----------

def test_pipeline_resumes_from_the_newest_readable_checkpoint(made, run, capsys):
    data, _ = made
    tear(run / "latest.pt")
    tear(run / "ckpt-000004.pt")
    intact = {p.name: p.read_bytes() for p in run.glob("ckpt-00000[123].pt")}
    train_stage(data, run, "tiny", ["train.steps=6", *STEPS])
    err = capsys.readouterr().err
    assert "resuming from ckpt-000003.pt (step 3)" in err and "latest.pt" in err and "ckpt-000004.pt" in err
    assert "resuming at step 3 of 6" in err
    assert all((run / name).read_bytes() == b for name, b in intact.items())  # readable ones untouched
    assert read_checkpoint(run / "latest.pt")["step"] == 6
    assert read_checkpoint(run / "ckpt-000004.pt")["step"] == 4  # the torn one retrained, not kept torn
    assert steps_logged(run) == [1, 2, 3, 4, 5, 6]


def test_pipeline_skips_a_finished_run_with_a_torn_latest(made, run, capsys):
    data, _ = made
    tear(run / "latest.pt")
    ckpt = train_stage(data, run, "tiny", ["train.steps=4", *STEPS])
    assert ckpt == run / "ckpt-000004.pt" and read_checkpoint(ckpt)["step"] == 4
    assert "has reached step 4, skipping" in capsys.readouterr().err


def test_pipeline_refuses_a_run_trained_with_other_settings(made, run, capsys):
    data, _ = made
    before = {p.name: p.read_bytes() for p in run.glob("*.pt")}
    # finished: skipping it would report a result of other settings; unfinished: resuming would mix them
    for steps in (4, 6):
        capsys.readouterr()
        assert guarded(lambda: train_stage(data, run, "tiny", [f"train.steps={steps}", *STEPS, "train.lr_init=0.01"])) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "other settings" in err[0] and "train.lr_init" in err[0], err
        assert f"delete {run} " in err[0], err
    assert {p.name: p.read_bytes() for p in run.glob("*.pt")} == before
    # settings that change nothing learned (the step count, logging, threads) are not a difference
    train_stage(data, run, "tiny", ["train.steps=5", *STEPS, "train.threads=1", "train.log_every=2"])
    assert read_checkpoint(run / "latest.pt")["step"] == 5


def test_pipeline_with_no_readable_checkpoint_stops_and_keeps_them(made, tmp_path, capsys):
    data, _ = made
    run = tmp_path / "run"
    run.mkdir()
    for name in ("latest.pt", "ckpt-000002.pt"):
        (run / name).write_text("junk")
    assert guarded(lambda: train_stage(data, run, "tiny", ["train.steps=4", *STEPS])) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: nothing to resume") and "ckpt-000002.pt" in err[0], err
    assert (run / "ckpt-000002.pt").read_text() == "junk"


def test_gns_train_resume_with_a_torn_latest(made, run, capsys):
    data, _ = made
    tear(run / "latest.pt")
    gns_main(["train", "--data", str(data), "--out", str(run), "--steps", "5", "--resume"])
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("warning: resuming from ckpt-000004.pt (step 4)") and "unreadable" in out[0]
    assert read_checkpoint(run / "latest.pt")["step"] == 5


# ---- 6. a torn last line of metrics.jsonl ------------------------------------------------------

def test_resume_drops_a_torn_metrics_line(made, run, capsys):
    data, _ = made
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"step": 5, "lo')
    gns_main(["train", "--data", str(data), "--out", str(run), "--steps", "5", "--resume"])
    out = capsys.readouterr().out
    assert "warning: dropped 1 unreadable line" in out
    assert steps_logged(run) == [1, 2, 3, 4, 5]


# ---- 4. overwrite guards ----------------------------------------------------------------------

@pytest.mark.parametrize("where", ["same", "inside", "around"])
def test_rollout_out_overlapping_the_data_is_refused(made, tmp_path, capsys, where):
    _, run = made
    data = Path(shutil.copytree(made[0], tmp_path / "d" / "data"))
    shards = sorted(p.name for p in data.iterdir())
    out = {"same": data, "inside": data / "roll", "around": tmp_path / "d"}[where]
    line = one_error(capsys, ["rollout", "--run", run, "--data", data, "--split", "valid", "--out", out, "--overwrite"])
    assert "overlap" in line
    assert sorted(p.name for p in data.iterdir()) == shards and Dataset(data).num_scenes("train") == 4


def test_rollout_overwrite_replaces_only_its_own_output(made, tmp_path, capsys):
    data, run = made
    other = Path(shutil.copytree(data, tmp_path / "other"))  # a dataset, not a rollout
    line = one_error(capsys, ["rollout", "--run", run, "--data", data, "--split", "valid", "--out", other, "--overwrite"])
    assert "only replaces an earlier gns rollout output" in line and Dataset(other).num_scenes("train") == 4
    out = tmp_path / "roll"
    args = ["rollout", "--run", str(run), "--data", str(data), "--split", "valid", "--out", str(out)]
    gns_main(args)
    gns_main(args + ["--overwrite"])  # an earlier rollout is replaced
    assert Dataset(out).num_scenes("valid") == 4
    (out / "notes.txt").write_text("mine")
    line = one_error(capsys, args + ["--overwrite"])
    assert "notes.txt" in line and (out / "notes.txt").read_text() == "mine"


def test_export_never_replaces_a_checkpoint(run, capsys):
    before = (run / "ckpt-000002.pt").read_bytes()
    line = one_error(capsys, ["export", "--run", run, "--out", run / "ckpt-000002.pt"])
    assert "exists" in line
    line = one_error(capsys, ["export", "--run", run, "--out", run / "ckpt-000002.pt", "--overwrite"])
    assert "not an exported gns model" in line
    assert (run / "ckpt-000002.pt").read_bytes() == before
    gns_main(["export", "--run", str(run), "--out", str(run / "model.pt")])
    gns_main(["export", "--run", str(run), "--out", str(run / "model.pt"), "--overwrite"])  # its own: replaced


def test_eval_json_replaces_only_an_earlier_eval(made, tmp_path, capsys):
    data, run = made
    copy = Path(shutil.copytree(data, tmp_path / "data"))
    meta = (copy / "metadata.json").read_text()
    line = one_error(capsys, ["eval", "--run", run, "--data", copy, "--split", "valid", "--json", copy / "metadata.json"])
    assert "not a gns eval output" in line and (copy / "metadata.json").read_text() == meta
    args = ["eval", "--run", str(run), "--data", str(data), "--split", "valid", "--json", str(tmp_path / "r.json")]
    gns_main(args)
    gns_main(args)  # its own earlier output is replaced
    assert json.loads((tmp_path / "r.json").read_text())["num_scenes"] == 4


def test_pipeline_fresh_deletes_only_its_own_folder(tmp_path, capsys):
    out = tmp_path / "mine"
    (out / "data").mkdir(parents=True)
    (out / "thesis.tex").write_text("years of work")
    assert movi_a.main(["--preset", "tiny", "--out", str(out), "--fresh"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fresh refuses" in err[0] and "thesis.tex" in err[0]
    assert (out / "thesis.tex").read_text() == "years of work"


# ---- 8. diverging rollouts ---------------------------------------------------------------------

@pytest.fixture
def diverging(monkeypatch):
    """A model whose acceleration is infinite on every other object of a batch (scenes 0 and 2
    of the valid split, one object each, rolled out in order) or, with all=True, on every object."""
    real = LearnedSimulator.predict_acceleration
    mode = {"all": False}

    def huge(self, history, graph):
        acc = real(self, history, graph)
        blow = torch.ones_like(graph.node_graph, dtype=torch.bool) if mode["all"] else graph.node_graph % 2 == 0
        return torch.where(blow[:, None], torch.full_like(acc, torch.inf), acc)

    monkeypatch.setattr(LearnedSimulator, "predict_acceleration", huge)
    return mode


def test_eval_reports_diverged_scenes_and_scores_the_rest(made, tmp_path, capsys, diverging):
    data, run = made
    results, pred, *_ = evaluate_run(run, data, "valid", progress=False)
    assert results["diverged_scenes"] == [0, 2] and results["num_diverged"] == 2 and results["num_scenes"] == 2
    assert np.isfinite(results["position_error_pct"]) and len(pred) == 2
    gns_main(["eval", "--run", str(run), "--data", str(data), "--split", "valid", "--json", str(tmp_path / "r.json")])
    cap = capsys.readouterr()
    assert "diverged: 2 of 4 scenes" in cap.out and cap.err.count("2 of 4 rollouts diverged") == 2
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["diverged_scenes"] == [0, 2] and saved["num_scenes"] == 2


def test_rollout_leaves_out_diverged_scenes_with_a_line(made, tmp_path, capsys, diverging):
    data, run = made
    gns_main(["rollout", "--run", str(run), "--data", str(data), "--split", "valid", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert "warning: 2 of 4 rollouts diverged" in err and "not written" in err
    back = Dataset(tmp_path / "r")
    assert back.num_scenes("valid") == 2 and back.meta["rollout"]["diverged"] == [0, 2]
    assert all(np.isfinite(sc.positions).all() for sc in back.load("valid"))


def test_every_rollout_diverging_is_one_line(made, tmp_path, capsys, diverging):
    data, run = made
    diverging["all"] = True
    line = one_error(capsys, ["eval", "--run", run, "--data", data, "--split", "valid"], code=1)
    assert "every rollout diverged (4 scenes" in line
    line = one_error(capsys, ["rollout", "--run", run, "--data", data, "--split", "valid", "--out", tmp_path / "r"],
                     code=1)
    assert "every rollout diverged" in line and not (tmp_path / "r").exists()


# ---- 11. one line instead of a traceback -------------------------------------------------------

def test_unwritable_outputs_fail_before_the_work(made, tmp_path, capsys):
    data, run = made
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    common = ["--run", run, "--data", data, "--split", "valid"]
    for argv in (["train", "--data", data, "--out", blocker / "run", "--config", TINY, "--steps", 2],
                 ["eval", *common, "--json", blocker / "r.json"],
                 ["eval", *common, "--plots", blocker / "plots"],
                 ["rollout", *common, "--out", blocker / "roll"],
                 ["export", "--run", run, "--out", blocker / "m.pt"]):
        line = one_error(capsys, argv)
        assert "cannot write to the" in line and "a_file" in line, line
    assert movi_a.main(["--preset", "tiny", "--out", str(blocker / "m")]) == 2
    assert "cannot write to the output folder" in capsys.readouterr().err


def test_cuda_device_without_cuda(made, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    data, _ = made
    line = one_error(capsys, ["train", "--data", data, "--out", tmp_path / "r", "--config", TINY,
                              "--set", "train.device=cuda"])
    assert "CUDA is not available" in line and not (tmp_path / "r").exists()


def test_resume_from_an_exported_model(made, tmp_path, capsys):
    data, run = made
    gns_main(["export", "--run", str(run), "--out", str(tmp_path / "exp" / "latest.pt")])
    line = one_error(capsys, ["train", "--data", data, "--out", tmp_path / "exp", "--steps", 6, "--resume"])
    assert "is an exported model" in line and "cannot resume" in line and "gns eval" in line


def test_damaged_weights_are_one_line(run, made, capsys):
    ckpt = torch.load(run / "latest.pt", weights_only=True)
    ckpt["model"]["target_normalizer.sum"] = torch.zeros(())
    torch.save(ckpt, run / "latest.pt")
    line = one_error(capsys, ["eval", "--run", run, "--data", made[0], "--split", "valid"])
    assert "damaged checkpoint" in line


def test_single_object_model_on_multi_object_scenes_warns(made, tmp_path, capsys):
    data, run = made
    ds = Dataset(data)
    one = ds.load("valid")
    # two of the single-cube tosses side by side, 10 units apart, as one two-object scene
    pair = [Scene(*(np.concatenate([getattr(a, k), getattr(b, k) + (10.0 if k == "positions" else 0.0)], axis=1)
                    for k in ("positions", "quaternions", "velocities", "angular_velocities")),
                  a.shape + b.shape, a.material + b.material,
                  *(np.concatenate([getattr(a, k), getattr(b, k)]) for k in ("scale", "mass", "friction", "restitution")))
            for a, b in ((one[0], one[1]), (one[2], one[3]))]
    multi = tmp_path / "multi"
    multi.mkdir()
    write_shard(multi / "test-00000.h5", pair, ds.meshes)
    meta = {k: v for k, v in ds.meta.items() if k not in ("splits", "format_version")}
    write_metadata(multi, {**meta, "splits": {"test": {"num_scenes": 2, "shards": ["test-00000.h5"]}}})
    capsys.readouterr()
    gns_main(["eval", "--run", str(run), "--data", str(multi)])
    err = [line for line in capsys.readouterr().err.splitlines() if "collision" in line]
    assert len(err) == 1 and err[0].startswith("warning: 2 of 2 scenes hold several objects")
    assert "no collision edges" in err[0] and "pass through each other" in err[0]
    gns_main(["rollout", "--run", str(run), "--data", str(multi), "--out", str(tmp_path / "r")])
    assert "no collision edges" in capsys.readouterr().err


def test_a_killed_rollouts_leftover_is_replaced_by_overwrite(made, tmp_path, capsys):
    """A gns rollout killed after writing shards but before metadata.json (the last file written)."""
    data, run = made
    out = tmp_path / "roll"
    args = ["rollout", "--run", str(run), "--data", str(data), "--split", "valid", "--out", str(out)]
    gns_main(args)
    (out / "metadata.json").unlink()
    (out / ".valid-00001.h5.k1ll3d.tmp").write_bytes(b"\x89HDF torn")    # atomic_file's temporary, torn
    line = one_error(capsys, args)
    assert "holds an unfinished gns rollout" in line and "use --overwrite" in line
    gns_main(args + ["--overwrite"])
    assert Dataset(out).num_scenes("valid") == 4 and sorted(p.name for p in out.iterdir()) == ["metadata.json",
                                                                                               "valid-00000.h5"]
    # a leftover holding anything else, or shards that gns rollout did not write, is still refused
    (out / "metadata.json").unlink()
    (out / "notes.txt").write_text("mine")
    assert "not one" in one_error(capsys, args + ["--overwrite"]) and (out / "notes.txt").read_text() == "mine"
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    shutil.copy(Path(data) / "valid-00000.h5", theirs / "valid-00000.h5")   # a dataset's shard, no metadata
    line = one_error(capsys, [*args[:-1], str(theirs), "--overwrite"])
    assert "not one" in line and (theirs / "valid-00000.h5").exists()


def test_eval_and_rollout_refuse_a_shard_changed_since_it_was_written(made, tmp_path, capsys):
    """The fingerprint they would record describes the data as written, not as it is now."""
    from datagen.inspect import inspect
    from datagen.shards import read_shard
    data, run = made
    copy = Path(shutil.copytree(data, tmp_path / "data"))
    scenes, meshes = read_shard(copy / "train-00000.h5")
    scenes[0].positions[3:] += 0.01                                 # valid data, not the data that was written
    write_shard(copy / "train-00000.h5", scenes, meshes)
    assert inspect(copy)[1]["changed_shards"] == ["train-00000.h5"]   # what datagen inspect reports (exit 3)
    for command in (["eval"], ["rollout", "--out", str(tmp_path / "roll")]):
        line = one_error(capsys, [*command, "--run", run, "--data", copy, "--split", "valid"])
        assert "train-00000.h5" in line and "changed since it was written" in line and "datagen inspect" in line
    assert not (tmp_path / "roll").exists()
    # a dataset written before checksums were recorded has nothing to compare: its fingerprint is computed
    meta = json.loads((copy / "metadata.json").read_text())
    del meta["checksums"], meta["fingerprint"]
    (copy / "metadata.json").write_text(json.dumps(meta))
    results, *_ = evaluate_run(run, copy, "valid", progress=False)
    assert results["data_fingerprint"] == Dataset(copy).fingerprint
