"""Importer of Kubric's MOVi-A records (google-research/kubric, challenges/movi) into our format.

Two source layouts, both one scene each, mixed freely in one source folder:
- a Kubric scene folder (what `movi_ab_worker.py` writes and the TFDS builder reads): a folder
  holding `metadata.json` with `instances`, a list of objects each with `positions` (T, 3),
  `quaternions` (T, 4, w x y z), `velocities`, `angular_velocities` (T, 3, world frame),
  `bboxes_3d` (T, 8, 3), `mass`, `friction`, `restitution`, `shape`, `material`; and `flags`
  with `frame_rate` (12 in MOVi-A);
- an `.npz` file holding one example of the published TFDS dataset as `tfds.as_numpy` gives it,
  flattened with "/" between keys: `instances/positions` (K, T, 3), `instances/quaternions`,
  `instances/velocities`, `instances/angular_velocities`, `instances/bboxes_3d` (K, T, 8, 3),
  `instances/mass`, `friction`, `restitution` (K,), `instances/shape_label` and
  `instances/material_label` (K, class indices into SHAPE_LABELS and MATERIAL_LABELS). The
  TFDS records do not hold the frame rate: --frame-rate (default MOVi-A's 12).

The scale of each object is its bounding box's largest edge (`bboxes_3d` at frame 0), since our
unit assets span 1: so the import needs no assumption about the size of Kubric's own assets.
Kubric's `cube` becomes `beveled_cube` unless told otherwise (CLEVR's cube is bevelled; every
MOVi-A model of the zoo is trained on it). Only the objects a record lists are imported: Kubric
keeps the instances visible in some frame, so an object never seen by the camera is absent
although it moved the others. The floor and gravity are MOVi-A's (z = 0, friction 0.3,
restitution 0.5, gravity -10).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from plumbing import DataError, check_output_folder
from datagen.scenes import get_shape
from datagen.output import new_dataset
from datagen.shards import METADATA_FILE, Scene, continuous, shard_name, write_metadata, write_shard

SHAPE_LABELS = ("cube", "cylinder", "sphere")      # the TFDS ClassLabel order of shape_label
MATERIAL_LABELS = ("metal", "rubber")
FLOOR = {"z": 0.0, "friction": 0.3, "restitution": 0.5}
GRAVITY = [0.0, 0.0, -10.0]
FRAME_RATE = 12.0
SHARD_SIZE = 50
ARRAYS = ("positions", "quaternions", "velocities", "angular_velocities", "bboxes_3d")
SCALARS = ("mass", "friction", "restitution")


def _bbox_width(corners: np.ndarray) -> float:
    """The largest edge of a box given by its 8 corners (8, 3), whatever its rotation: each
    corner's three nearest others are its edges."""
    d = np.linalg.norm(corners[:, None] - corners[None], axis=-1)
    return float(np.sort(d, axis=1)[:, 1:4].max())


def _from_folder(folder: Path) -> tuple[list[dict], float | None]:
    try:
        meta = json.loads((folder / "metadata.json").read_text())
        return list(meta["instances"]), (meta.get("flags") or {}).get("frame_rate")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(f"{folder / 'metadata.json'}: not a Kubric scene's metadata ({e})") from None


def _from_npz(path: Path) -> tuple[list[dict], None]:
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
        count = len(data["instances/positions"])
        objects = []
        for k in range(count):
            obj = {key: data[f"instances/{key}"][k] for key in (*ARRAYS, *SCALARS)}
            obj["shape"] = SHAPE_LABELS[int(data["instances/shape_label"][k])]
            obj["material"] = MATERIAL_LABELS[int(data["instances/material_label"][k])]
            objects.append(obj)
    except (OSError, ValueError, KeyError, IndexError) as e:
        raise DataError(f"{path}: not a flattened MOVi-A TFDS example ({type(e).__name__}: {e})") from None
    return objects, None


def record_to_scene(objects: list[dict], name: str, cube_as: str) -> Scene:
    """One Kubric record's instances as a Scene; DataError naming the record on a bad one."""
    if not objects:
        raise DataError(f"{name}: no instances")
    try:
        arrays = {k: np.stack([np.asarray(o[k], np.float64) for o in objects], axis=1) for k in ARRAYS}
        scalars = {k: np.array([float(o[k]) for o in objects]) for k in SCALARS}
        shapes = [str(o["shape"]).lower() for o in objects]
        materials = [str(o["material"]).lower() for o in objects]
    except (KeyError, ValueError, TypeError) as e:
        raise DataError(f"{name}: an instance lacks or mangles {e}") from None
    T = arrays["positions"].shape[0]
    expected = {"positions": (T, len(objects), 3), "quaternions": (T, len(objects), 4),
                "velocities": (T, len(objects), 3), "angular_velocities": (T, len(objects), 3),
                "bboxes_3d": (T, len(objects), 8, 3)}
    for key, shape in expected.items():
        if arrays[key].shape != shape or not np.isfinite(arrays[key]).all():
            raise DataError(f"{name}: instances' {key} is {arrays[key].shape} or not finite; expected {shape}")
    unknown = sorted(set(shapes) - set(SHAPE_LABELS))
    if unknown:
        raise DataError(f"{name}: shape {unknown[0]!r} is not one of MOVi-A's {', '.join(SHAPE_LABELS)}")
    norms = np.linalg.norm(arrays["quaternions"], axis=-1)
    if np.abs(norms - 1).max() > 1e-3:
        raise DataError(f"{name}: quaternions are not unit (|q| up to {norms.max():.4f})")
    quats = continuous(arrays["quaternions"] / norms[..., None])
    return Scene(positions=arrays["positions"], quaternions=quats, velocities=arrays["velocities"],
                 angular_velocities=arrays["angular_velocities"],
                 shape=[cube_as if s == "cube" else s for s in shapes], material=materials,
                 scale=np.array([_bbox_width(arrays["bboxes_3d"][0, n]) for n in range(len(objects))]),
                 attrs={"source_record": name}, **scalars)


def list_records(src: Path) -> list[Path]:
    """The scene folders (holding metadata.json) and .npz files directly in src, sorted by name."""
    if not src.is_dir():
        raise DataError(f"Kubric source folder does not exist: {src}")
    found = sorted(p for p in src.iterdir() if (p.is_dir() and (p / "metadata.json").is_file()) or p.suffix == ".npz")
    if not found:
        raise DataError(f"{src}: no Kubric scene folders (with metadata.json) or .npz examples in it")
    return found


def import_kubric(src: str | Path, out: str | Path, split: str = "test", frame_rate: float | None = None,
                  cube_as: str = "beveled_cube", overwrite: bool = False, progress: bool = True) -> dict:
    """Convert every Kubric record in src into a dataset folder of our format (all into `split`);
    returns its metadata. Every record is read and checked before anything is written."""
    from tqdm import tqdm

    src, out = Path(src), Path(out)
    if cube_as not in ("cube", "beveled_cube"):
        raise DataError(f"--cube-as must be cube or beveled_cube, got {cube_as!r}")
    records = list_records(src)
    check_output_folder(out, overwrite, "use --overwrite to replace it")
    scenes, rates = [], set()
    for path in tqdm(records, desc="reading Kubric records", disable=not progress, unit="scene"):
        objects, rate = _from_folder(path) if path.is_dir() else _from_npz(path)
        if rate is not None:
            rates.add(float(rate))
        scenes.append(record_to_scene(objects, path.name, cube_as))
    if len(rates) > 1:
        raise DataError(f"{src}: the records have different frame rates ({', '.join(map(str, sorted(rates)))})")
    recorded = rates.pop() if rates else None
    if frame_rate is not None and recorded is not None and abs(frame_rate - recorded) > 1e-9:
        raise DataError(f"--frame-rate {frame_rate:g}, but the records say {recorded:g}")
    rate = frame_rate or recorded or FRAME_RATE
    names = sorted({s for sc in scenes for s in sc.shape})
    meshes = {n: (get_shape(n).vertices, get_shape(n).faces) for n in names}
    with new_dataset(out, overwrite) as written:
        shards = []
        for k in range(0, len(scenes), SHARD_SIZE):
            shards.append(shard_name(split, k // SHARD_SIZE))
            write_shard(out / shards[-1], scenes[k:k + SHARD_SIZE], meshes, attrs={"split": split, "source": "kubric"})
            written.append(out / shards[-1])
        lengths = [sc.num_frames for sc in scenes]
        write_metadata(out, {
            "generator": "datagen import kubric", "source": "kubric", "source_path": str(src),
            "frame_rate": rate, "gravity": GRAVITY, "floor": dict(FLOOR), "quaternion_order": "wxyz",
            "materials_vary": len({(f, r) for sc in scenes for f, r in zip(sc.friction, sc.restitution)}) > 1,
            "shapes": {n: {"num_vertices": len(v), "num_faces": len(f)} for n, (v, f) in meshes.items()},
            "num_frames": {"min": min(lengths), "max": max(lengths)},
            "splits": {split: {"num_scenes": len(scenes), "shards": shards,
                               "records": [sc.attrs["source_record"] for sc in scenes]}}})
    return json.loads((out / METADATA_FILE).read_text())
