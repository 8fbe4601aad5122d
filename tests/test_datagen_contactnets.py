"""Importer of the ContactNets cube tosses, on three real tosses copied into tests/data."""
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen import contactnets
from datagen.contactnets import import_contactnets, list_toss_ids, read_toss
from plumbing import DataError
from datagen.shards import Dataset
from gns.geometry import quat_multiply, quat_conjugate, quat_to_matrix
from gns.metrics import evaluate_scenes

SRC = Path(__file__).parent / "data" / "contactnets"
IDS = [55, 229, 274]


def raw(i):
    return torch.load(SRC / "tosses_processed" / f"{i}.pt", weights_only=True).numpy()[0]


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    out = tmp_path_factory.mktemp("cn") / "ds"
    meta = import_contactnets(SRC, out, progress=False)
    return out, meta


def by_id(ds, split="test"):
    return {sc.attrs["toss_id"]: sc for sc in ds.load(split)}


def test_list_toss_ids():
    assert list_toss_ids(SRC) == IDS
    assert list_toss_ids(SRC / "tosses_processed") == IDS


def test_import_round_trip_poses(imported):
    out, meta = imported
    ds = Dataset(out)
    assert ds.splits == ["test"] and ds.num_scenes("test") == 3
    assert meta["splits"]["test"]["shards"] == ["test-00000.h5"]
    scenes = by_id(ds)
    for i in IDS:
        a, sc = raw(i), scenes[i]
        assert sc.positions.shape == (a.shape[0], 1, 3)
        assert np.array_equal(sc.positions[:, 0], a[:, 0:3])
        assert np.allclose(sc.quaternions[:, 0], a[:, 3:7], atol=1e-12)
        assert np.array_equal(sc.velocities[:, 0], a[:, 7:10])
        assert sc.shape == ["cube"] and sc.material == ["acrylic"]
        assert sc.scale.tolist() == [2.0] and sc.mass.tolist() == [0.37]
        assert sc.friction.tolist() == [0.18] and sc.restitution.tolist() == [0.125]
        assert sc.attrs["source_file"] == f"{i}.pt"


def test_metadata(imported):
    out, meta = imported
    ds = Dataset(out)
    assert ds.frame_rate == pytest.approx(148.0)
    assert np.allclose(ds.gravity, [0, 0, -187.21374045801525])
    assert ds.floor == {"z": 0.0, "friction": 0.18, "restitution": 0.125}
    assert ds.materials_vary is False
    assert meta["source"] == "contactnets" and meta["units"].startswith("cube half-widths")
    assert meta["splits"]["test"]["toss_ids"] == IDS


def test_cube_corners_at_plus_minus_one(imported):
    ds = Dataset(imported[0])
    verts, faces = ds.meshes["cube"]
    sc = ds.load("test", limit=1)[0]
    body = sc.scale[0] * verts
    assert body.shape == (8, 3) and np.array_equal(np.abs(body), np.ones((8, 3)))


def test_angular_velocity_converted_to_world(imported):
    scenes = by_id(Dataset(imported[0]))
    for i in IDS:
        a = raw(i)
        expect = np.einsum("tij,tj->ti", quat_to_matrix(a[:, 3:7]), a[:, 10:13])
        assert np.allclose(scenes[i].angular_velocities[:, 0], expect, atol=1e-12)
    # The data really is body frame: during the free flight before the first bounce, the world
    # angular velocity from quaternion differences, 2 dq/dt conj(q), matches the converted one.
    a, dt = raw(229), 1 / 148
    q = a[:12, 3:7]
    w_fd = 2 * quat_multiply((q[2:] - q[:-2]) / (2 * dt), quat_conjugate(q[1:-1]))[:, 1:]
    w_world = scenes[229].angular_velocities[1:11, 0]
    assert np.median(np.linalg.norm(w_fd - w_world, axis=1)) < 0.2 * np.median(np.linalg.norm(w_world, axis=1))
    assert np.median(np.linalg.norm(w_fd - a[1:11, 10:13], axis=1)) > 0.5  # the raw body vector is not world


def test_local_matrix_matches_geometry():
    q = np.random.default_rng(0).normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert np.allclose(contactnets._quat_to_matrix(q), quat_to_matrix(q))


def test_true_penetration_floor_of_resting_tosses(imported):
    # The measured cube rests at z ~ 0.97 instead of 1: about 1.5% of the width (data README).
    scenes = list(by_id(Dataset(imported[0])).values())
    r = evaluate_scenes(scenes, scenes, Dataset(imported[0]).meshes)
    assert 1.0 < r["true_penetration_pct"] < 2.0
    assert r["position_error_pct"] == 0.0 and r["rotation_error_deg"] < 1e-6
    for sc in scenes:
        assert 0.9 < sc.positions[-1, 0, 2] < 1.0  # ends resting on the table


def test_split_mapping_and_shard_size(tmp_path):
    meta = import_contactnets(SRC, tmp_path / "a", splits={"train": [229, 55], "test": [274]}, progress=False)
    ds = Dataset(tmp_path / "a")
    assert ds.splits == ["train", "test"]
    assert meta["splits"]["train"]["toss_ids"] == [229, 55]
    meta = import_contactnets(SRC, tmp_path / "b", ids=[274, 55, 229], shard_size=2, progress=False)
    assert meta["splits"]["test"]["shards"] == ["test-00000.h5", "test-00001.h5"]
    assert [sc.attrs["toss_id"] for sc in Dataset(tmp_path / "b").load("test")] == IDS
    with pytest.raises(ValueError, match="both"):
        import_contactnets(SRC, tmp_path / "c", splits={"train": [55], "test": [55]}, progress=False)
    with pytest.raises(ValueError, match="either"):
        import_contactnets(SRC, tmp_path / "c", ids=[55], splits={"train": [55]}, progress=False)
    with pytest.raises(DataError, match="not found"):
        import_contactnets(SRC, tmp_path / "c", ids=[55, 9999], progress=False)
    assert not (tmp_path / "c").exists()


# ---- bad inputs: DataError with a one-line message naming the file, nothing written ---------

def make_src(tmp_path, tensors: dict):
    """A source folder with the good tosses plus the given {name: object} saved with torch.save."""
    src = tmp_path / "src"
    shutil.copytree(SRC, src)
    for name, obj in tensors.items():
        torch.save(obj, src / "tosses_processed" / f"{name}.pt")
    return src


def good(i=55):
    return torch.from_numpy(raw(i)[None].copy())


def corrupt(fn, i=55):
    t = good(i)
    fn(t)
    return t


BAD = {
    "nan row": (lambda: corrupt(lambda t: t[0, 10].fill_(float("nan"))), "NaN or inf .* frame 10"),
    "inf": (lambda: corrupt(lambda t: t[0, 3, 1].fill_(float("inf"))), "NaN or inf"),
    "non-unit quaternion": (lambda: corrupt(lambda t: t[0, 20, 3:7].mul_(1.01)), "quaternion norm 1.01 at frame 20"),
    "too short": (lambda: good()[:, :3], "only 3 frames"),
    "wrong shape": (lambda: good()[:, :, :12], r"shape \(1, 86, 12\)"),
    "not a tensor": (lambda: {"x": 1}, "holds a dict"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_toss_raises_and_writes_nothing(tmp_path, case):
    make, pattern = BAD[case]
    src = make_src(tmp_path, {"900": make()})
    out = tmp_path / "out"
    with pytest.raises(DataError, match=pattern) as e:
        import_contactnets(src, out, progress=False)
    msg = str(e.value)
    assert "900.pt" in msg and "\n" not in msg
    assert not out.exists()
    # An empty output folder given by the user stays empty.
    out.mkdir()
    with pytest.raises(DataError):
        import_contactnets(src, out, progress=False)
    assert list(out.iterdir()) == []


def test_unreadable_file(tmp_path):
    src = make_src(tmp_path, {})
    (src / "tosses_processed" / "901.pt").write_bytes(b"not a torch file")
    with pytest.raises(DataError, match="901.pt: not a readable torch tensor file") as e:
        import_contactnets(src, tmp_path / "out", progress=False)
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()


def test_nearly_unit_quaternion_is_renormalised(tmp_path):
    src = make_src(tmp_path, {"902": corrupt(lambda t: t[0, :, 3:7].mul_(1.0005))})
    a = read_toss(src / "tosses_processed" / "902.pt")
    assert np.allclose(np.linalg.norm(a[:, 3:7], axis=1), 1.0)
    assert np.allclose(a[:, 3:7], raw(55)[:, 3:7], atol=1e-12)


def test_min_frames(tmp_path):
    with pytest.raises(DataError, match="55.pt: only 86 frames, need at least 100"):
        import_contactnets(SRC, tmp_path / "out", min_frames=100, progress=False)
    assert not (tmp_path / "out").exists()


def test_missing_source_folder(tmp_path):
    with pytest.raises(DataError, match="source folder does not exist"):
        import_contactnets(tmp_path / "nowhere", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no tosses"):
        import_contactnets(tmp_path / "empty", tmp_path / "out", progress=False)


def test_existing_output_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="not empty"):
        import_contactnets(SRC, out, progress=False)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    # overwrite replaces the dataset files only, and keeps the rest
    (out / "test-00005.h5").write_bytes(b"stale")
    import_contactnets(SRC, out, ids=[55], overwrite=True, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "notes.txt", "test-00000.h5"]
    assert Dataset(out).num_scenes("test") == 1
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match="not a folder"):
        import_contactnets(SRC, tmp_path / "file", overwrite=True, progress=False)


def test_constants_fall_back_to_published_values(tmp_path):
    src = make_src(tmp_path, {})
    (src / "params_processed" / "experiment.json").write_text('{"dt": 0.006756756756756757, "mass": 0.37}')
    meta = import_contactnets(src, tmp_path / "a", ids=[55], progress=False)
    assert meta["gravity"][2] == pytest.approx(-9.81 / 0.0524)
    assert meta["floor"]["friction"] == 0.18
    shutil.rmtree(src / "params_processed")
    with pytest.warns(UserWarning, match="experiment.json"):
        meta = import_contactnets(src, tmp_path / "b", ids=[55], progress=False)
    assert meta["frame_rate"] == pytest.approx(148.0)


def test_cli_messages_name_the_cli_flags(tmp_path, capsys):
    """A file holding more than tensors is one short line naming --allow-pickle (not PyTorch's
    paragraph on weights_only); a taken --out names --overwrite."""
    from datagen.cli import main
    src = make_src(tmp_path, {"903": np.zeros((1, 86, 19))})   # a numpy array: pickled, not a tensor
    out = tmp_path / "out"
    assert main(["import", "contactnets", str(src), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "903.pt" in err[0], err
    assert "--allow-pickle" in err[0] and "weights_only" not in err[0] and len(err[0].replace(str(src), "")) < 160, err[0]
    assert not out.exists()
    assert main(["import", "contactnets", str(src), "--out", str(out), "--quiet", "--allow-pickle"]) == 2
    assert "903.pt: holds a ndarray" in capsys.readouterr().err
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["import", "contactnets", str(SRC), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0] and "overwrite=True to" not in err[0], err
