"""Issue 60: runs that share an output folder at once cannot mix datasets, a Ray address where
no cluster answers fails fast, and no shard changed since it was written is ever folded into
the checksums and the fingerprint (resume, finalising, inspect). Plus the floor's extent."""
import json
import multiprocessing as mp
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import pytest

from datagen import toss as gen_mod
from datagen import output as output_mod
from datagen.cli import main
from datagen.shards import Dataset, write_shard

SMALL = ["--scenes", "4", "--valid", "2", "--frames", "5", "--scenes-per-shard", "2", "--quiet"]
ROOT = Path(__file__).resolve().parent.parent


def toss(out, *extra):
    return main(["toss", "--out", str(out), *SMALL, *extra])


def files(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(root.iterdir())}


def only_error_line(text, *words):
    err = text.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    for w in words:
        assert w in err[0], err[0]
    return err[0]


def one_seed(out: Path) -> int:
    """The folder is one dataset: inspect passes and every shard is of the metadata's seed."""
    meta = json.loads((out / "metadata.json").read_text())
    for p in out.glob("*.h5"):
        with h5py.File(p) as f:
            assert int(f.attrs["seed"]) == meta["seed"], (p.name, int(f.attrs["seed"]), meta["seed"])
    return meta["seed"]


def _run_forked(argv, barrier, errfile):
    """main(argv) in a forked child whose first metadata write waits (2 s at most) for the other
    child's: both have looked at the folder before either wrote, the race made certain."""
    import sys as child_sys
    child_sys.stderr = open(errfile, "w")
    real = output_mod.write_metadata
    first = [True]

    def slowed(out, meta):
        if first[0]:
            first[0] = False
            try:
                barrier.wait(timeout=2)
            except threading.BrokenBarrierError:
                pass
        return real(out, meta)
    output_mod.write_metadata = slowed
    try:
        code = main(argv)
    except BaseException as e:  # noqa: BLE001 - reported through the exit code
        print(f"crash: {type(e).__name__}: {e}", file=child_sys.stderr)
        code = 99
    child_sys.stderr.flush()
    os._exit(code)


def race(tmp_path, argvs):
    ctx = mp.get_context("fork")
    barrier = ctx.Barrier(len(argvs))
    errs = [tmp_path / f"err{k}" for k in range(len(argvs))]
    procs = [ctx.Process(target=_run_forked, args=(a, barrier, e)) for a, e in zip(argvs, errs)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    return [p.exitcode for p in procs], [e.read_text() for e in errs]


def test_two_whole_runs_at_once_cannot_both_fill_one_folder(tmp_path):
    out = tmp_path / "d"
    codes, errs = race(tmp_path, [["toss", "--out", str(out), *SMALL, "--seed", s] for s in ("1", "2")])
    assert sorted(codes) == [0, 2], (codes, errs)
    loser = codes.index(2)
    only_error_line(errs[loser], "another `datagen toss` is writing", "seed differs")
    assert main(["inspect", str(out)]) == 0
    assert one_seed(out) == (2 if loser == 0 else 1)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]     # no lock file left


def test_two_parts_of_other_seeds_at_once_cannot_mix(tmp_path):
    out = tmp_path / "d"
    parts = [["toss", "--out", str(out), *SMALL, "--seed", s, "--shard-index", i, "--num-shards", "2"]
             for s, i in (("1", "0"), ("2", "1"))]
    codes, errs = race(tmp_path, parts)
    assert sorted(codes) == [0, 2], (codes, errs)
    loser = codes.index(2)
    only_error_line(errs[loser], "cannot add shards to", "its seed differs")
    seed = one_seed(out)
    assert seed == (2 if loser == 0 else 1)
    # the loser's part, rerun with the winner's seed, completes the one dataset
    assert toss(out, "--seed", str(seed), "--shard-index", str(loser), "--num-shards", "2") == 0
    assert main(["inspect", str(out)]) == 0 and one_seed(out) == seed


def test_whole_runs_started_together_as_processes(tmp_path):
    """No hook: two real commands started at once, a few times; at most one succeeds, and what
    is left is one dataset."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for trial in range(2):
        out = tmp_path / f"d{trial}"
        procs = [subprocess.Popen([sys.executable, "-m", "datagen.cli", "toss", "--out", str(out), *SMALL,
                                   "--seed", s], env=env, stderr=subprocess.PIPE, text=True) for s in ("1", "2")]
        results = [(p.wait(120), p.stderr.read()) for p in procs]
        codes = [c for c, _ in results]
        assert codes.count(0) <= 1, results
        for c, err in results:
            if c:
                only_error_line(err)
        if 0 in codes:
            assert main(["inspect", str(out)]) == 0
            one_seed(out)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ray_address_where_no_cluster_answers_fails_fast_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "d"
    start = time.monotonic()
    assert toss(out, "--backend", "ray", "--ray-address", f"127.0.0.1:{_free_port()}") == 2
    assert time.monotonic() - start < 20
    only_error_line(capsys.readouterr().err, "cannot reach the Ray cluster", "nothing answers")
    assert not out.exists()


def test_ray_address_that_accepts_but_never_answers_times_out(tmp_path):
    """A port that accepts connections but is no Ray cluster: the bounded wait, a setting."""
    out = tmp_path / "d"
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        port = listener.getsockname()[1]
        env = {**os.environ, "PYTHONPATH": str(ROOT), "DATAGEN_RAY_CONNECT_TIMEOUT": "3"}
        start = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "datagen.cli", "toss", "--out", str(out), *SMALL,
                            "--backend", "ray", "--ray-address", f"127.0.0.1:{port}"],
                           env=env, capture_output=True, text=True, timeout=90)
    assert time.monotonic() - start < 30
    assert r.returncode == 2
    only_error_line(r.stderr, "no answer within 3 s")
    assert not out.exists()


def test_ray_address_without_the_ray_backend_is_one_line(tmp_path, capsys):
    assert toss(tmp_path / "d", "--ray-address", "auto") == 2
    only_error_line(capsys.readouterr().err, "--ray-address needs --backend ray")
    assert not (tmp_path / "d").exists()


def _edit(out: Path, name: str) -> None:
    """A shard still valid, no longer the same data: as a hand edit leaves it."""
    from datagen.shards import read_shard
    scenes, meshes = read_shard(out / name)
    scenes[0].positions[2, 0, 0] += 1e-6
    write_shard(out / name, scenes, meshes, {"seed": 7})


def _interrupted(out, monkeypatch, after=3):
    real = gen_mod.simulate
    calls = {"n": 0}

    def dies(spec, cfg):
        calls["n"] += 1
        if calls["n"] == after:
            raise KeyboardInterrupt
        return real(spec, cfg)
    monkeypatch.setattr(gen_mod, "simulate", dies)
    assert toss(out, "--seed", "7") == 2
    monkeypatch.setattr(gen_mod, "simulate", real)


def test_resume_refuses_a_kept_shard_edited_since_it_was_written(tmp_path, capsys, monkeypatch):
    out = tmp_path / "d"
    _interrupted(out, monkeypatch)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "train-00000.h5"]
    _edit(out, "train-00000.h5")
    before = files(out)
    capsys.readouterr()
    assert toss(out, "--seed", "7", "--resume") == 2
    only_error_line(capsys.readouterr().err, "train-00000.h5 changed since it was written")
    assert files(out) == before
    # moved away, it is made again and the dataset is the one the seed makes
    (out / "train-00000.h5").unlink()
    assert toss(out, "--seed", "7", "--resume") == 0
    ref = tmp_path / "ref"
    assert toss(ref, "--seed", "7") == 0
    assert {k: v for k, v in files(out).items() if k != "metadata.json"} == \
           {k: v for k, v in files(ref).items() if k != "metadata.json"}
    assert Dataset(out).fingerprint == Dataset(ref).fingerprint


def test_resume_makes_again_a_kept_shard_with_no_recorded_checksum(tmp_path, capsys, monkeypatch):
    """An interrupted folder of an older datagen (no checksums recorded): its kept shards are
    made again, never trusted, so an edit does not survive."""
    out = tmp_path / "d"
    _interrupted(out, monkeypatch)
    meta = json.loads((out / "metadata.json").read_text())
    del meta["written"]
    (out / "metadata.json").write_text(json.dumps(meta))
    _edit(out, "train-00000.h5")
    assert toss(out, "--seed", "7", "--resume") == 0
    ref = tmp_path / "ref"
    assert toss(ref, "--seed", "7") == 0
    assert (out / "train-00000.h5").read_bytes() == (ref / "train-00000.h5").read_bytes()
    assert Dataset(out).fingerprint == Dataset(ref).fingerprint


@pytest.mark.parametrize("rerun", [["--resume"], ["--shard-index", "1", "--num-shards", "2"]])
def test_finalising_a_complete_dataset_with_an_edited_shard_refuses(tmp_path, capsys, rerun):
    out = tmp_path / "d"
    if "--resume" in rerun:
        assert toss(out, "--seed", "7") == 0
    else:
        for part in ("0", "1"):
            assert toss(out, "--seed", "7", "--shard-index", part, "--num-shards", "2") == 0
    _edit(out, "train-00000.h5")               # part 0's shard: a rerun of part 1 finalises over it
    before = files(out)
    capsys.readouterr()
    assert toss(out, "--seed", "7", *rerun) == 2
    only_error_line(capsys.readouterr().err, "train-00000.h5 changed since it was written")
    assert files(out) == before                # metadata.json keeps the evidence


def test_a_rerun_on_a_complete_unchanged_dataset_rewrites_nothing(tmp_path):
    out = tmp_path / "d"
    assert toss(out, "--seed", "7") == 0
    before = files(out)
    assert toss(out, "--seed", "7", "--resume") == 0
    assert toss(out, "--seed", "7", "--shard-index", "0", "--num-shards", "2") == 0
    assert files(out) == before


def test_inspect_exits_non_zero_on_a_shard_changed_since_writing(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out, "--seed", "7") == 0
    _edit(out, "valid-00000.h5")
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("changed: 1 shard(s)") and "valid-00000.h5" in err[0], err


def test_a_spawn_box_beyond_the_physics_floor_is_refused(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out, "--set", "spawn.low=[10000.0, 10000.0, 1.0]", "spawn.high=[10001.0, 10001.0, 2.0]") == 2
    only_error_line(capsys.readouterr().err, "beyond the physics floor", "10001")
    assert not out.exists()
    # without a floor nothing is declared, and a far spawn is the user's choice
    assert toss(out, "--scenes", "1", "--valid", "0", "--set", "floor.enabled=false",
                "spawn.low=[10000.0, 10000.0, 1.0]", "spawn.high=[10001.0, 10001.0, 2.0]") == 0


def test_an_object_tossed_off_the_floor_is_refused(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out, "--scenes", "1", "--valid", "0", "--set", "spawn.velocity_low=[6000.0, 0.0, 0.0]",
                "spawn.velocity_high=[6000.0, 0.0, 0.0]") == 2
    # refused from the config, before a scene is simulated or a file written
    only_error_line(capsys.readouterr().err, "can fly", "beyond the physics floor")
    assert not out.exists()


def test_kill_9_leaves_a_claim_that_resume_takes_over(tmp_path):
    """A run killed with SIGKILL leaves its lock files but no lock (the kernel drops it): the
    resume at once, while the dead run's pool workers may still be ending, finishes the dataset
    the seed makes and removes them."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    args = ["--scenes", "120", "--frames", "40", "--scenes-per-shard", "2", "--quiet", "--seed", "5", "--workers", "2"]
    out = tmp_path / "d"
    p = subprocess.Popen([sys.executable, "-m", "datagen.cli", "toss", "--out", str(out), *args], env=env,
                         stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while len(list(out.glob("*.h5"))) < 3 and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.02)
    p.kill()
    p.wait()
    assert len(list(out.glob("*.h5"))) < 60, "the run ended before it was killed: make it longer"
    assert main(["toss", "--out", str(out), *args, "--resume"]) == 0
    ref = tmp_path / "ref"
    assert main(["toss", "--out", str(ref), *args]) == 0
    mine, theirs = files(out), files(ref)
    assert json.loads(mine.pop("metadata.json"))["fingerprint"] == json.loads(theirs.pop("metadata.json"))["fingerprint"]
    assert mine == theirs                                  # no lock file left either


def test_a_file_system_without_flock_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    import errno
    import fcntl

    from datagen.cli import main as datagen_main

    def no_flock(fd, how):
        raise OSError(errno.ENOSYS, "Function not implemented")
    monkeypatch.setattr(fcntl, "flock", no_flock)
    out = tmp_path / "d"
    assert datagen_main(["toss", "--out", str(out), "--scenes", "1", "--frames", "4", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not support flock" in err[0], err
    assert not out.exists() or not any(out.iterdir())


def test_tosses_that_would_fly_off_the_floor_are_refused_before_anything_is_written(tmp_path, capsys):
    from datagen.cli import main as datagen_main
    out = tmp_path / "d"
    # the spawn box is on the floor, but tosses heading to the centre overshoot it within 4 s
    code = datagen_main(["toss", "--out", str(out), "--scenes", "1", "--frames", "48", "--quiet",
                         "--set", "spawn.low=[600,600,1]", "spawn.high=[600,600,2]"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "can fly" in err[0] and "beyond the physics floor" in err[0], err
    assert not out.exists()
