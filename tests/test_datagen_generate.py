"""Distributed generation: --shard-index/--num-shards (Slurm arrays), resume, the Ray backend,
and the provenance and fingerprint every dataset records. The promise under test: however the
work is divided, the folder ends up byte for byte the dataset one run writes."""
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from datagen import toss as gen_mod
from datagen.cli import main
from datagen.shards import Dataset
from plumbing import DataError

SMALL = ["--scenes", "6", "--valid", "2", "--test", "1", "--frames", "6", "--scenes-per-shard", "2", "--quiet"]
LIBRARIES = ("python", "torch", "numpy", "pybullet", "h5py", "trimesh", "scipy")


def toss(out, *extra):
    return main(["toss", "--out", str(out), *SMALL, *extra])


def files(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(root.iterdir())}


def only_error_line(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    for w in words:
        assert w in err[0], err[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The dataset one run writes (process pool, 2 workers): 3 train, 1 valid, 1 test shards."""
    out = tmp_path_factory.mktemp("ref") / "d"
    assert toss(out, "--seed", "7", "--workers", "2") == 0
    return out


class CountScenes:
    def __init__(self, monkeypatch):
        self.n = 0
        real = gen_mod.simulate

        def counted(spec, cfg):
            self.n += 1
            return real(spec, cfg)
        monkeypatch.setattr(gen_mod, "simulate", counted)


def test_sharded_runs_make_the_same_bytes_as_one_run(reference, tmp_path, capsys):
    out = tmp_path / "d"
    # out of order, as an array's tasks may finish
    for part in ("2", "0"):
        assert toss(out, "--seed", "7", "--shard-index", part, "--num-shards", "3") == 0
        assert "still missing" in capsys.readouterr().out
        assert json.loads((out / "metadata.json").read_text())["complete"] is False
        with pytest.raises(DataError, match="incomplete dataset"):
            Dataset(out)
    # plan positions: train-0..2 are 0..2, valid-0 is 3, test-0 is 4; parts 2 and 0 have 2, 0 and 3
    assert sorted(p.name for p in out.glob("*.h5")) == ["train-00000.h5", "train-00002.h5", "valid-00000.h5"]
    assert toss(out, "--seed", "7", "--shard-index", "1", "--num-shards", "3") == 0
    assert "fingerprint" in capsys.readouterr().out
    assert files(out) == files(reference)            # shards and metadata.json, byte for byte
    assert Dataset(out).meta["complete"] is True
    assert main(["inspect", str(out)]) == 0


def test_a_rerun_part_redoes_only_its_missing_shards(reference, tmp_path, monkeypatch):
    out = tmp_path / "d"
    assert toss(out, "--seed", "7", "--shard-index", "0", "--num-shards", "2") == 0    # shards 0, 2, 4
    (out / "train-00002.h5").unlink()                  # as if the task was killed before this one
    count = CountScenes(monkeypatch)
    assert toss(out, "--seed", "7", "--shard-index", "0", "--num-shards", "2") == 0
    assert count.n == 2                                # one shard of 2 scenes, not the part's 5 scenes
    assert toss(out, "--seed", "7", "--shard-index", "1", "--num-shards", "2") == 0
    assert files(out) == files(reference)


def test_resume_finishes_a_partly_sharded_folder_and_a_lost_shard(reference, tmp_path, monkeypatch):
    out = tmp_path / "d"
    assert toss(out, "--seed", "7", "--shard-index", "1", "--num-shards", "2") == 0    # shards 1, 3
    count = CountScenes(monkeypatch)
    assert toss(out, "--seed", "7", "--resume") == 0   # the whole command finishes the rest
    assert count.n == 5                                # shards 0, 2, 4 only
    assert files(out) == files(reference)
    (out / "train-00001.h5").unlink()                  # a shard lost from a finished dataset
    count.n = 0
    assert toss(out, "--seed", "7", "--resume") == 0
    assert count.n == 2 and files(out) == files(reference)


@pytest.mark.parametrize("args, words", [
    (["--shard-index", "0"], ["--shard-index and --num-shards go together"]),
    (["--num-shards", "2"], ["--shard-index and --num-shards go together"]),
    (["--shard-index", "2", "--num-shards", "2"], ["--shard-index must be in 0..1"]),
    (["--shard-index", "-1", "--num-shards", "2"], ["--shard-index must be in 0..1"]),
    (["--shard-index", "0", "--num-shards", "2", "--overwrite"], ["--overwrite cannot be used with --num-shards"]),
])
def test_bad_sharding_is_one_line_and_writes_nothing(tmp_path, capsys, args, words):
    out = tmp_path / "d"
    assert toss(out, *args) == 2
    only_error_line(capsys, *words)
    assert not out.exists()


def test_a_part_of_another_plan_is_refused(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out, "--seed", "7", "--shard-index", "0", "--num-shards", "2") == 0
    capsys.readouterr()
    before = files(out)
    assert toss(out, "--seed", "8", "--shard-index", "1", "--num-shards", "2") == 2
    only_error_line(capsys, "cannot add shards to", "its seed differs")
    assert files(out) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    assert toss(mine, "--shard-index", "0", "--num-shards", "2") == 2
    only_error_line(capsys, "not a dataset's")
    assert [p.name for p in mine.iterdir()] == ["thesis.tex"]


def test_metadata_records_versions_commit_and_a_fingerprint(reference, tmp_path):
    meta = Dataset(reference).meta
    versions = meta["provenance"]["versions"]
    assert all(isinstance(versions[k], str) and versions[k] for k in LIBRARIES), versions
    assert versions["python"] == ".".join(map(str, sys.version_info[:3]))
    code = meta["provenance"]["code"]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(gen_mod.__file__).parent, capture_output=True, text=True)
    if head.returncode == 0:                           # the suite runs from a checkout (CI clones one)
        assert code["commit"] == head.stdout.strip() and isinstance(code["dirty"], bool)
    assert sorted(meta["checksums"]) == sorted(p.name for p in reference.glob("*.h5"))
    assert re.fullmatch(r"[0-9a-f]{64}", meta["fingerprint"])
    # the fingerprint is recomputable from the folder, and changes with the data
    ds = Dataset(reference)
    del ds.meta["fingerprint"]
    assert ds.fingerprint == meta["fingerprint"]
    other = tmp_path / "other"
    assert toss(other, "--seed", "8") == 0
    assert Dataset(other).fingerprint != meta["fingerprint"]


def test_inspect_names_shards_changed_since_the_fingerprint(tmp_path, capsys):
    from datagen.shards import write_shard
    out = tmp_path / "d"
    assert toss(out, "--seed", "7") == 0
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    assert "shards match their checksums" in capsys.readouterr().out
    ds = Dataset(out)
    scenes = ds.load("valid")
    scenes[0].positions[2, 0, 0] += 1e-9           # still valid data, no longer the same data
    write_shard(out / "valid-00000.h5", scenes, ds.meshes)
    assert main(["inspect", str(out)]) == 3               # valid, but not what the fingerprint names
    assert "1 shard(s) changed since: valid-00000.h5" in capsys.readouterr().out
    ds = Dataset(out)
    del ds.meta["fingerprint"]
    assert ds.fingerprint != Dataset(out).fingerprint     # recomputed from the shards as they are now


def test_no_commit_outside_a_checkout(tmp_path):
    """An installed copy (no git checkout around it) records code: null instead of failing."""
    import plumbing
    src = Path(plumbing.__file__)
    (tmp_path / "plumbing.py").write_text(src.read_text())
    spec = importlib.util.spec_from_file_location("copied_plumbing", tmp_path / "plumbing.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.code_version() is None
    assert mod.provenance()["versions"]["numpy"]


def test_ray_backend_without_ray_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)      # as if the extra were not installed
    assert toss(tmp_path / "d", "--backend", "ray") == 2
    only_error_line(capsys, "--backend ray needs Ray", "rigid-gns[ray]")
    assert not (tmp_path / "d").exists()


def test_ray_backend_on_a_local_cluster_gives_the_same_bytes(reference, tmp_path):
    # ray is in the dev extra, so this runs wherever the README's test command ran: not skipped.
    import ray  # noqa: F401
    out = tmp_path / "d"
    assert toss(out, "--seed", "7", "--backend", "ray", "--workers", "2") == 0
    assert files(out) == files(reference)


def test_keeping_freed_heap_memory_changes_no_byte(reference, tmp_path):
    """datagen.toss.keep_freed_memory only changes how the C heap gives memory back; a run
    with glibc's defaults (DATAGEN_KEEP_HEAP=0, a fresh process) writes the same dataset."""
    import os
    out = tmp_path / "default_heap"
    run = subprocess.run([sys.executable, "-m", "datagen.cli", "toss", "--out", str(out), *SMALL, "--seed", "7",
                          "--workers", "2"], env={**os.environ, "DATAGEN_KEEP_HEAP": "0"}, check=True,
                         capture_output=True, text=True)
    assert run.stderr == ""     # --quiet, and the pool's workers stop without a word
    ours, theirs = files(out), files(reference)
    strip = lambda b: {k: v for k, v in json.loads(b).items() if k != "provenance"}  # noqa: E731
    assert strip(ours.pop("metadata.json")) == strip(theirs.pop("metadata.json"))
    assert ours == theirs
