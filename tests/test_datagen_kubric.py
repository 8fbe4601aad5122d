"""The Kubric MOVi-A importer: records written in Kubric's two layouts (a scene folder's
metadata.json, a TFDS example flattened to .npz) from scenes we simulated, imported back."""
import json

import numpy as np
import pytest

from datagen.toss import generate
from datagen.kubric import MATERIAL_LABELS, SHAPE_LABELS, import_kubric
from datagen.scenes import get_shape, load_config
from datagen.shards import Dataset
from datagen.toss import rotate
from plumbing import DataError


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    root = tmp_path_factory.mktemp("kubric")
    cfg = load_config(None, ["scene.frames=6", "scene.shapes=['beveled_cube', 'sphere', 'cylinder']",
                             'scene.objects="3-4"'])
    generate(cfg, 4, {"train": 0, "valid": 0, "test": 2}, root / "ours", progress=False)
    return Dataset(root / "ours").load("test")


def kubric_instances(sc):
    """Our scene as Kubric lists its instances: world bounding-box corners, Kubric's shape names."""
    out = []
    for n in range(sc.num_objects):
        v = get_shape(sc.shape[n]).vertices * sc.scale[n]
        lo, hi = v.min(0), v.max(0)
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        corners = rotate(sc.quaternions[:, n], box[None]) + sc.positions[:, n, None]
        out.append({"positions": sc.positions[:, n], "quaternions": sc.quaternions[:, n],
                    "velocities": sc.velocities[:, n], "angular_velocities": sc.angular_velocities[:, n],
                    "bboxes_3d": corners, "mass": sc.mass[n], "friction": sc.friction[n],
                    "restitution": sc.restitution[n], "material": sc.material[n],
                    "shape": "cube" if sc.shape[n] == "beveled_cube" else sc.shape[n]})
    return out


def write_folder(path, sc):
    path.mkdir(parents=True)
    instances = [{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in o.items()}
                 for o in kubric_instances(sc)]
    (path / "metadata.json").write_text(json.dumps({"flags": {"frame_rate": 12, "step_rate": 240},
                                                    "metadata": {"num_frames": sc.num_frames},
                                                    "instances": instances}, default=float))


def write_npz(path, sc):
    objs = kubric_instances(sc)
    data = {f"instances/{k}": np.stack([o[k] for o in objs]).astype(np.float32)
            for k in ("positions", "quaternions", "velocities", "angular_velocities", "bboxes_3d",
                      "mass", "friction", "restitution")}
    data["instances/shape_label"] = np.array([SHAPE_LABELS.index(o["shape"]) for o in objs])
    data["instances/material_label"] = np.array([MATERIAL_LABELS.index(o["material"]) for o in objs])
    np.savez(path, **data)


def test_both_layouts_import_to_the_scenes_they_were_written_from(truth, tmp_path):
    src = tmp_path / "src"
    write_folder(src / "0000", truth[0])
    write_npz(src / "0001.npz", truth[1])
    meta = import_kubric(src, tmp_path / "out", progress=False)
    assert meta["frame_rate"] == 12 and meta["splits"]["test"]["records"] == ["0000", "0001.npz"]
    got = Dataset(tmp_path / "out").load("test")
    for want, have, tol in zip(truth, got, (1e-9, 1e-5)):      # the .npz holds float32, as TFDS does
        np.testing.assert_allclose(have.positions, want.positions, atol=tol)
        np.testing.assert_allclose(have.quaternions, want.quaternions, atol=tol)
        np.testing.assert_allclose(have.angular_velocities, want.angular_velocities, atol=1e-4)
        np.testing.assert_allclose(have.scale, want.scale, rtol=1e-5)      # from the bounding boxes
        assert have.shape == want.shape and have.material == want.material
        np.testing.assert_allclose(have.friction, want.friction, rtol=1e-6)


def test_a_bad_record_is_refused_in_one_line_and_nothing_is_written(truth, tmp_path):
    src = tmp_path / "src"
    write_folder(src / "0000", truth[0])
    meta = json.loads((src / "0000" / "metadata.json").read_text())
    meta["instances"][1]["shape"] = "teapot"
    (src / "0000" / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="'teapot' is not one of MOVi-A's"):
        import_kubric(src, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no Kubric scene folders"):
        import_kubric(tmp_path / "empty", tmp_path / "x", progress=False)


def test_the_cli_imports_and_gns_eval_scores_the_import(truth, tmp_path, capsys):
    from datagen.cli import main as datagen
    from gns.cli import main as gns
    write_folder(tmp_path / "src" / "a", truth[0])
    assert datagen(["import", "kubric", str(tmp_path / "src"), "--out", str(tmp_path / "k"), "--quiet"]) == 0
    gns(["eval", "--run", "movi_a", "--data", str(tmp_path / "k"), "--json", str(tmp_path / "r.json")])
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["num_scenes"] == 1 and results["num_objects"] == truth[0].num_objects
