"""`datagen toss` / `datagen inspect` end to end: determinism, the format, and bad input."""
import errno
import hashlib
import json
import os

import h5py
import numpy as np
import pytest
from datagen_helpers import sigterm_toss

from datagen import toss as gen_mod
from datagen.cli import main
from datagen.output import recorded_checksums
from datagen.shards import Dataset, Scene, write_shard

SMALL = ["--scenes", "6", "--valid", "2", "--test", "2", "--frames", "8", "--scenes-per-shard", "3", "--quiet"]


def toss(out, *extra):
    return main(["toss", "--out", str(out), *SMALL, *extra])


def arrays(root):
    ds = Dataset(root)
    return [(split, sc) for split in ds.splits for sc in ds.load(split)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "d"
    assert toss(out, "--seed", "3") == 0
    return out


def test_all_shapes_sizes_materials_pass_inspect(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["toss", "--out", str(out), "--shapes", "cube,beveled_cube,cylinder,sphere", "--sizes", "small,large",
                 "--materials", "metal,rubber", "--scenes", "24", "--quiet", "--seed", "1"]) == 0
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ok: no problems found" in text
    ds = Dataset(out)
    assert set(ds.meshes) == {"cube", "beveled_cube", "cylinder", "sphere"}
    assert ds.meta["materials_vary"] is True
    assert ds.meta["shapes"]["cube"]["num_vertices"] == 8


def test_metadata_records_seed_config_and_rates(dataset):
    ds = Dataset(dataset)
    m = ds.meta
    assert m["seed"] == 3 and m["frame_rate"] == 12 and m["physics_rate"] == 240
    assert m["config"]["scene"]["frames"] == 8 and m["gravity"] == [0, 0, -10]
    assert {s: m["splits"][s]["num_scenes"] for s in ("train", "valid", "test")} == {"train": 6, "valid": 2, "test": 2}
    sc = ds.load("train")[0]
    assert sc.positions.shape == (8, 1, 3) and sc.quaternions.shape == (8, 1, 4)
    with h5py.File(dataset / "train-00000.h5") as f:  # the raw file, as docs/data_format.md reads it
        assert f.attrs["quaternion_order"] == "wxyz"
        s = 1
        T, N, r0 = f["scenes/num_frames"][s], f["scenes/num_objects"][s], f["scenes/state_start"][s]
        pos = f["states/positions"][r0:r0 + T * N].reshape(T, N, 3)
    np.testing.assert_array_equal(pos, ds.load("train")[1].positions)


def test_same_seed_same_arrays_whatever_the_worker_count(dataset, tmp_path):
    other = tmp_path / "w2"
    assert toss(other, "--seed", "3", "--workers", "2") == 0
    a, b = arrays(dataset), arrays(other)
    assert len(a) == len(b) == 10
    for (sa, x), (sb, y) in zip(a, b):
        assert sa == sb and x.shape == y.shape
        for k in ("positions", "quaternions", "velocities", "angular_velocities", "mass", "scale"):
            assert np.array_equal(getattr(x, k), getattr(y, k)), k


def test_another_seed_gives_other_scenes(dataset, tmp_path):
    other = tmp_path / "s4"
    assert toss(other, "--seed", "4") == 0
    a, b = arrays(dataset), arrays(other)
    assert not any(np.array_equal(x.positions, y.positions) for (_, x), (_, y) in zip(a, b))


def test_multi_object_scenes_do_not_overlap(tmp_path):
    out = tmp_path / "m"
    assert main(["toss", "--out", str(out), "--objects", "3-10", "--scenes", "4", "--frames", "4", "--quiet"]) == 0
    from datagen.scenes import get_shape
    for sc in Dataset(out).load("train"):
        assert 3 <= sc.num_objects <= 10
        p = sc.positions[0]
        r = np.array([s * np.linalg.norm(get_shape(n).vertices, axis=1).max() for n, s in zip(sc.shape, sc.scale)])
        d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(len(p)) * 1e9
        assert (d > r[:, None] + r[None]).all()


def only_error_line(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    for w in words:
        assert w in err[0], err[0]


@pytest.mark.parametrize("args, words", [
    (["--shapes", "cube,pyramid"], ["unknown shape 'pyramid'"]),
    (["--materials", "wood"], ["unknown material 'wood'"]),
    (["--sizes", "huge"], ["unknown size 'huge'"]),
    (["--scenes", "-3"], ["must be >= 0"]),
    (["--scenes", "0"], ["nothing to generate"]),
    (["--objects", "5-3"], ["objects range"]),
    (["--set", "sizes.small=-0.7"], ["'sizes.small' must be finite > 0"]),
    (["--set", "sizes.small=inf"], ["'sizes.small' must be finite > 0"]),
    (["--set", "floor.restitution=5"], ["'floor.restitution' must be finite >= 0 and <= 1"]),
    (["--set", "floor.friction=-0.1"], ["'floor.friction' must be finite >= 0"]),
    (["--set", "materials.metal.density=0"], ["'materials.metal.density' must be finite > 0"]),
    (["--set", "physics.gravity=[0, 0, nan]"], ["'physics.gravity' must be finite"]),
    (["--set", "physics.ccd=no"], ["'physics.ccd' must be true or false, got 'no'"]),
    (["--set", "floor.enabled=1"], ["'floor.enabled' must be true or false"]),
    (["--set", "scene.frames=4.5"], ["'scene.frames' must be a whole number"]),
    (["--set", "floor.friction=0.5", "physics.ccd=maybe"], ["'physics.ccd' must be true or false"]),
    (["--set", "scene.frmes=3"], ["unknown config key 'scene.frmes'", "did you mean 'frames'"]),
    (["--set", "spawn.low=[5, 5, 5]", "--set", "spawn.high=[1, 1, 1]"], ["spawn.low must be <= spawn.high"]),
    (["--frame-rate", "7"], ["whole multiple"]),
    (["--workers", "0"], ["--workers must be >= 1"]),
    (["--config", "/nonexistent.toml"], ["config file not found"]),
])
def test_bad_input_one_line_no_files(tmp_path, capsys, args, words):
    out = tmp_path / "bad"
    assert main(["toss", "--out", str(out), "--scenes", "2", "--frames", "4", "--quiet", *args]) == 2
    only_error_line(capsys, *words)
    assert not out.exists() or not any(out.glob("*.h5"))


def test_existing_output_is_refused_then_overwritten(dataset, tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out) == 0
    assert toss(out) == 2
    only_error_line(capsys, "exists and is not empty", "--resume", "--overwrite")
    assert toss(out, "--overwrite", "--seed", "9") == 0
    assert Dataset(out).meta["seed"] == 9


@pytest.mark.skipif(os.name != "posix", reason="signals between processes")
def test_sigterm_stops_the_pool_and_leaves_only_whole_shards(tmp_path):
    """SIGTERM to a run on a process pool: one error line, the workers gone, no temporary file of
    a worker stopped mid-write, and every shard left is whole (its recorded checksum)."""
    out = tmp_path / "d"
    status, err = sigterm_toss(out, "--scenes", "4000", "--valid", "0", "--test", "0", "--frames", "12",
                               "--scenes-per-shard", "2", "--workers", "2", "--quiet", shards=2)
    assert status == 2
    assert err.strip().splitlines() == ["error: interrupted; no partial shard was left (rerun with --resume to finish)"]
    assert not list(out.glob(".*.tmp"))
    recorded = recorded_checksums(json.loads((out / "metadata.json").read_text()))
    kept = sorted(out.glob("*.h5"))
    assert 2 <= len(kept) < 2000
    for p in kept:
        assert hashlib.sha256(p.read_bytes()).hexdigest() == recorded[p.name]


def test_interrupted_run_leaves_no_partial_shard_and_resumes(tmp_path, capsys, monkeypatch):
    out = tmp_path / "d"
    real = gen_mod.simulate
    calls = {"n": 0}

    def dies_in_the_second_shard(spec, cfg):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real(spec, cfg)

    monkeypatch.setattr(gen_mod, "simulate", dies_in_the_second_shard)
    assert toss(out) == 2
    only_error_line(capsys, "interrupted", "--resume")
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "train-00000.h5"]
    with pytest.raises(Exception, match="incomplete dataset"):
        Dataset(out)
    monkeypatch.setattr(gen_mod, "simulate", real)
    assert toss(out, "--resume") == 0
    assert main(["inspect", str(out)]) == 0
    ref = tmp_path / "ref"
    assert toss(ref) == 0
    for (_, x), (_, y) in zip(arrays(out), arrays(ref)):
        assert np.array_equal(x.positions, y.positions)


def test_full_disk_is_one_line_and_no_partial_file(tmp_path, capsys, monkeypatch):
    out = tmp_path / "d"
    real = h5py.File.create_dataset if hasattr(h5py.File, "create_dataset") else None

    def no_space(self, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(h5py.Group, "create_dataset", no_space)
    assert toss(out) == 2
    only_error_line(capsys, "No space left on device")
    assert not list(out.glob("*.h5")) and not list(out.glob(".*.tmp"))
    del real


def test_inspect_reports_each_problem(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out) == 0
    ds = Dataset(out)
    scenes = ds.load("valid")
    scenes[0].positions[3, 0, 1] = np.nan
    scenes[1].quaternions[2, 0] *= 1.1
    write_shard(out / "valid-00000.h5", scenes, ds.meshes)
    sunk = ds.load("test")
    sunk[0].positions[:, 0, 2] = -5.0
    write_shard(out / "test-00000.h5", sunk, ds.meshes)
    with open(out / "train-00001.h5", "r+b") as f:
        f.truncate(200)
    (out / "train-00000.h5").unlink()
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 1
    err = capsys.readouterr().err
    assert "missing shard" in err and "train-00000.h5" in err
    assert "truncated shard" in err and "train-00001.h5" in err
    assert "valid-00000.h5 scene 0: positions contains NaN" in err
    assert "valid-00000.h5 scene 1: quaternions are not unit" in err
    assert "test-00000.h5 scene 0: object 0" in err and "below the floor" in err


def test_inspect_of_a_non_dataset(tmp_path, capsys):
    assert main(["inspect", str(tmp_path)]) == 1
    assert "not a dataset folder" in capsys.readouterr().err


def test_set_booleans_as_a_shell_user_writes_them(tmp_path):
    out = tmp_path / "nofloor"
    assert main(["toss", "--out", str(out), "--scenes", "1", "--frames", "4", "--quiet",
                 "--set", "floor.enabled=False", "physics.ccd=TRUE"]) == 0
    meta = Dataset(out).meta
    assert meta["floor"] is None and meta["config"]["physics"]["ccd"] is True


def test_overwrite_deletes_only_what_the_tool_wrote(tmp_path, capsys):
    out = tmp_path / "d"
    assert toss(out) == 0
    (out / "notes.txt").write_text("my notes")
    (out / "analysis.h5").write_bytes(b"user data")        # an .h5 the tool did not write
    (out / "plots").mkdir()
    (out / "plots" / "fig.png").write_bytes(b"png")
    assert toss(out, "--overwrite", "--seed", "5") == 0
    assert (out / "notes.txt").read_text() == "my notes"
    assert (out / "analysis.h5").read_bytes() == b"user data" and (out / "plots" / "fig.png").exists()
    assert Dataset(out).meta["seed"] == 5


def test_overwrite_refuses_a_folder_that_is_not_a_dataset(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "results.h5").write_bytes(b"not a shard")
    assert toss(out, "--overwrite") == 2
    only_error_line(capsys, "does not look like a dataset")
    assert (out / "results.h5").exists()


@pytest.mark.parametrize("meta, words", [
    ("[1, 2, 3]", "not a JSON object"),
    ('{"format_version": 1, "gravity": [0, 0, -10], "floor": null, "splits": {}}', "lacks 'frame_rate'"),
    ('{"format_version": 1, "frame_rate": 12, "gravity": [0, 0, -10], "floor": null, "splits": [1]}',
     "'splits' must map"),
])
def test_inspect_of_broken_metadata_is_one_line(tmp_path, capsys, meta, words):
    (tmp_path / "metadata.json").write_text(meta)
    assert main(["inspect", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    problems = [line for line in err.splitlines() if line.startswith("problem:")]
    assert len(problems) == 1 and words in problems[0] and "Traceback" not in err, err


def test_inspect_judges_imported_tosses_as_measurements(tmp_path, capsys):
    from pathlib import Path
    src = Path(__file__).parent / "data" / "contactnets"
    out = tmp_path / "cubes"
    assert main(["import", "contactnets", str(src), "--out", str(out), "--quiet"]) == 0
    ds = Dataset(out)
    scenes = ds.load("test")
    scenes[0].positions[:, 0, 2] -= 0.2                 # 10% of the width into the table: tracking
    write_shard(out / "test-00000.h5", scenes, ds.meshes)
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 3             # the edit is named (3), the sinking is no problem (1)
    said = capsys.readouterr().out
    assert "measured data: deepest point below the floor" in said and "max 1" in said
    scenes[1].positions[5, 0, 0] = np.nan               # corruption still fails
    write_shard(out / "test-00000.h5", scenes, ds.meshes)
    assert main(["inspect", str(out)]) == 1


def test_full_disk_at_the_file_write_is_one_line_and_resumable(tmp_path, capsys, monkeypatch):
    import builtins
    import datagen.shards as shards_mod
    real_open = builtins.open
    calls = {"n": 0}

    def fills_up(file, mode="r", *a, **k):
        f = real_open(file, mode, *a, **k)
        if "w" in mode and ".h5." in str(file) and str(file).endswith(".tmp"):    # a shard being written
            calls["n"] += 1
            if calls["n"] > 1:                      # the second shard finds the disk full half-way
                f.write(b"partial")
                f.close()
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))
        return f
    monkeypatch.setattr(shards_mod, "open", fills_up, raising=False)
    out = tmp_path / "d"
    assert toss(out, "--scenes-per-shard", "1") == 2
    only_error_line(capsys, "No space left on device", "--resume")
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    monkeypatch.undo()
    assert toss(out, "--scenes-per-shard", "1", "--resume") == 0
