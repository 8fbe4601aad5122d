"""Importer of the ContactNets real cube tosses (DAIRLab/contact-nets, BSD-3) into our format.

Source layout (the repository's `data/` folder, or any folder holding the same):
    <src>/tosses_processed/N.pt        one toss each: legacy torch.save of a float64 (1, T, 19)
    <src>/params_processed/experiment.json   constants: dt, g, mass, mu, restitution, ...
A flat folder of N.pt files (with experiment.json beside them) is accepted too.

Columns of a toss: 0:3 centre position, 3:7 quaternion w x y z, 7:10 linear velocity (world),
10:13 angular velocity in the BODY frame, 13:19 unused zeros. Units are cube half-widths
(1 = 0.0524 m) and seconds. Our format wants world-frame angular velocity, so it becomes
R(q) @ w_body. Each toss becomes one scene of one object: shape `cube` (the unit 8-vertex cube,
+-0.5) at scale 2, so its corners sit at +-1 half-widths as in the data.

Known quirks of the data (not changed here): the resting cube's centre sits at z ~ 0.978, so
the ground truth penetrates the table by ~1.5% of the width on average; and a few tosses are
copies of another toss rotated about the vertical axis (e.g. 229 and 456), which matters when
splitting into train and test.

torch is imported lazily, only to read the .pt files; the rest of `datagen` does not need it.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from plumbing import check_output_folder, DataError
from datagen.scenes import get_shape
from datagen.output import new_dataset
from datagen.shards import METADATA_FILE, SPLITS, Scene, shard_name, write_metadata, write_shard

HALF_WIDTH_M = 0.0524         # 1 data unit in metres (10.48 cm cube)
CUBE_SCALE = 2.0              # unit asset spans 1; the data's cube spans 2 half-widths
SHARD_SIZE = 64
QUAT_NORM_TOL = 1e-3          # renormalise within this of 1; beyond it the row is corrupt
MIN_FRAMES = 4                # 3 given frames + at least one to predict
# Published constants of the set-up, used only where experiment.json lacks them.
DEFAULTS = {"dt": 1.0 / 148.0, "g": 9.81 / HALF_WIDTH_M, "mass": 0.37, "mu": 0.18, "restitution": 0.125}
MATERIAL = "acrylic"


def _toss_dir(src_dir: Path) -> Path:
    src_dir = Path(src_dir)
    if not src_dir.is_dir():
        raise DataError(f"ContactNets source folder does not exist: {src_dir}")
    sub = src_dir / "tosses_processed"
    return sub if sub.is_dir() else src_dir


def list_toss_ids(src_dir: str | Path) -> list[int]:
    """Sorted integer ids N of the `N.pt` toss files under src_dir (or its tosses_processed/)."""
    ids = [int(p.stem) for p in _toss_dir(Path(src_dir)).glob("*.pt") if p.stem.isdigit()]
    return sorted(ids)


def read_experiment(src_dir: str | Path) -> dict:
    """The set-up constants: params_processed/experiment.json (or experiment.json in src_dir),
    completed with the published values for keys it lacks; a missing file warns and uses them."""
    src_dir = Path(src_dir)
    for p in (src_dir / "params_processed" / "experiment.json", src_dir / "experiment.json",
              src_dir.parent / "params_processed" / "experiment.json"):
        if p.is_file():
            try:
                consts = json.loads(p.read_text())
            except json.JSONDecodeError as e:
                raise DataError(f"{p}: invalid JSON ({e})") from None
            return {**DEFAULTS, **{k: v for k, v in consts.items() if k != "vertices"}}
    warnings.warn(f"no experiment.json under {src_dir}; using the published ContactNets constants")
    return dict(DEFAULTS)


def read_toss(path: str | Path, min_frames: int = MIN_FRAMES, allow_pickle: bool = False) -> np.ndarray:
    """Load and check one toss file -> (T, 13) float64 with unit quaternions.

    Raises DataError (one line naming the file) for an unreadable file, a wrong shape, NaN/inf,
    fewer than min_frames frames or a quaternion whose norm is off by more than 1e-3.
    allow_pickle=True lets torch unpickle arbitrary objects: only for files you trust.
    """
    import torch  # lazy: only the importer needs torch

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such toss file")
    try:
        # weights_only=True reads plain tensors (the ContactNets files) without running pickle code.
        data = torch.load(path, map_location="cpu", weights_only=not allow_pickle)
    except Exception as e:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for bad files
        text = str(e).strip()
        # torch's weights_only message is a paragraph about its own API; ours names what to do here
        if not allow_pickle and "Unsupported global" in text:
            raise DataError(f"{path}: holds Python objects besides tensors; if the file is trusted, pass "
                            "--allow-pickle (allow_pickle=True in Python)") from None
        if text.startswith("Weights only load failed"):
            reason = text.partition("WeightsUnpickler error:")[2].strip().splitlines()
            text = f"unpickling failed ({reason[0].strip()})" if reason else "unpickling failed"
        first = text.splitlines()[0][:200] if text else type(e).__name__
        raise DataError(f"{path}: not a readable torch tensor file: {first}") from None
    if not isinstance(data, torch.Tensor):
        raise DataError(f"{path}: holds a {type(data).__name__}, expected a tensor of shape (1, T, 19)")
    arr = data.detach().cpu().numpy().astype(np.float64)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2 or arr.shape[1] != 19:
        raise DataError(f"{path}: tensor of shape {tuple(data.shape)}, expected (1, T, 19)")
    arr = arr[:, :13]  # 13:19 is an unused control placeholder
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.unique(np.nonzero(bad)[0])
        raise DataError(f"{path}: NaN or inf in {len(rows)} frame(s), first at frame {rows[0]}")
    if arr.shape[0] < min_frames:
        raise DataError(f"{path}: only {arr.shape[0]} frames, need at least {min_frames}")
    norm = np.linalg.norm(arr[:, 3:7], axis=1)
    off = np.abs(norm - 1.0)
    if off.max() > QUAT_NORM_TOL:
        t = int(np.argmax(off))
        raise DataError(f"{path}: quaternion norm {norm[t]:.6g} at frame {t} (must be within {QUAT_NORM_TOL} of 1)")
    arr[:, 3:7] /= norm[:, None]
    return arr


def toss_to_scene(arr: np.ndarray, toss_id: int, source_file: str, consts: Mapping) -> Scene:
    """A checked (T, 13) toss -> a one-object Scene in our format (angular velocity to world)."""
    T = arr.shape[0]
    pos, quat, vel, w_body = arr[:, 0:3], arr[:, 3:7], arr[:, 7:10], arr[:, 10:13]
    w_world = np.einsum("tij,tj->ti", _quat_to_matrix(quat), w_body)
    return Scene(
        positions=pos.reshape(T, 1, 3).copy(),
        quaternions=quat.reshape(T, 1, 4).copy(),
        velocities=vel.reshape(T, 1, 3).copy(),
        angular_velocities=w_world.reshape(T, 1, 3),
        shape=["cube"],
        material=[MATERIAL],
        scale=np.array([CUBE_SCALE]),
        mass=np.array([float(consts["mass"])]),
        friction=np.array([float(consts["mu"])]),
        restitution=np.array([float(consts["restitution"])]),
        attrs={"scene_id": int(toss_id), "toss_id": int(toss_id), "source_file": source_file,
               "source": "contactnets"},
    )


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    # datagen must not import gns (the dependency points the other way), so a local copy of the
    # wxyz -> matrix formula; tests check it against gns.geometry.quat_to_matrix.
    w, x, y, z = np.moveaxis(q, -1, 0)
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    return r.reshape(r.shape[:-1] + (3, 3))


def _plan_splits(available: list[int], ids: Iterable[int] | None,
                 splits: Mapping[str, Iterable[int]] | None) -> dict[str, list[int]]:
    if splits is not None:
        if ids is not None:
            raise ValueError("give either ids or a split mapping, not both")
        unknown = set(splits) - set(SPLITS)
        if unknown:
            raise ValueError(f"unknown split(s) {sorted(unknown)}; splits are {', '.join(SPLITS)}")
        plan = {s: [int(i) for i in splits[s]] for s in SPLITS if s in splits}
        plan = {s: lst for s, lst in plan.items() if lst}
        seen: dict[int, str] = {}
        for s, lst in plan.items():
            for i in lst:
                if i in seen:
                    raise ValueError(f"toss {i} is in both {seen[i]!r} and {s!r}")
                seen[i] = s
    else:
        plan = {"test": sorted(int(i) for i in ids) if ids is not None else list(available)}
    missing = sorted(set(i for lst in plan.values() for i in lst) - set(available))
    if missing:
        raise DataError(f"toss id(s) not found in the source folder: {', '.join(map(str, missing[:10]))}"
                        + (" ..." if len(missing) > 10 else ""))
    if not any(plan.values()):
        raise DataError("no tosses to import")
    return plan


def _read_tosses(toss_dir: Path, plan: dict[str, list[int]], consts: Mapping, min_frames: int,
                 allow_pickle: bool, progress: bool) -> dict[str, list[Scene]]:
    """Every planned toss read, checked and converted, by split (DataError on the first bad one)."""
    from tqdm import tqdm

    scenes: dict[str, list[Scene]] = {}
    todo = [(s, i) for s, lst in plan.items() for i in lst]
    for s, i in tqdm(todo, desc="reading tosses", disable=not progress, unit="toss"):
        arr = read_toss(toss_dir / f"{i}.pt", min_frames=min_frames, allow_pickle=allow_pickle)
        scenes.setdefault(s, []).append(toss_to_scene(arr, i, f"{i}.pt", consts))
    return scenes


def _write_shards(out_dir: Path, scenes: dict[str, list[Scene]], meshes: dict, shard_size: int,
                  written: list[Path]) -> dict[str, dict]:
    """Write each split's shards, appending each path to `written` as it lands; returns the splits' metadata."""
    split_meta = {}
    for s, lst in scenes.items():
        names = []
        for k in range(0, len(lst), shard_size):
            name = shard_name(s, k // shard_size)
            write_shard(out_dir / name, lst[k:k + shard_size], meshes, attrs={"split": s, "source": "contactnets"})
            written.append(out_dir / name)
            names.append(name)
        split_meta[s] = {"num_scenes": len(lst), "shards": names, "toss_ids": [sc.attrs["toss_id"] for sc in lst]}
    return split_meta


def _metadata(scenes: dict[str, list[Scene]], consts: Mapping, split_meta: dict[str, dict]) -> dict:
    """The dataset's metadata.json (write_metadata adds checksums, fingerprint and provenance)."""
    lengths = [sc.num_frames for lst in scenes.values() for sc in lst]
    dt = float(consts["dt"])
    return {
        "source": "contactnets",
        "source_url": "https://github.com/DAIRLab/contact-nets (data/, BSD-3-Clause)",
        "units": f"cube half-widths (1 = {HALF_WIDTH_M} m)",
        "frame_rate": round(1.0 / dt, 9),
        "gravity": [0.0, 0.0, -float(consts["g"])],
        "floor": {"z": 0.0, "friction": float(consts["mu"]), "restitution": float(consts["restitution"])},
        "materials_vary": False,
        "shapes": ["cube"],
        "materials": [MATERIAL],
        "objects_per_scene": 1,
        "num_frames": {"min": int(min(lengths)), "max": int(max(lengths))},
        "angular_velocity_frame": "world (converted from the data's body frame)",
        "constants": {k: consts[k] for k in sorted(consts) if isinstance(consts[k], (int, float))},
        "splits": split_meta,
    }


def _write_dataset(out_dir: Path, scenes: dict[str, list[Scene]], consts: Mapping, overwrite: bool,
                   shard_size: int) -> None:
    """Shards, then metadata.json; on any failure removes what it wrote, and out_dir if it made it."""
    shape = get_shape("cube")
    meshes = {"cube": (shape.vertices, shape.faces)}
    with new_dataset(out_dir, overwrite) as written:
        split_meta = _write_shards(out_dir, scenes, meshes, shard_size, written)
        write_metadata(out_dir, _metadata(scenes, consts, split_meta))


def import_contactnets(src_dir: str | Path, out_dir: str | Path, ids: Iterable[int] | None = None,
                       overwrite: bool = False, progress: bool = True,
                       splits: Mapping[str, Iterable[int]] | None = None, min_frames: int = MIN_FRAMES,
                       shard_size: int = SHARD_SIZE, allow_pickle: bool = False) -> dict:
    """Convert ContactNets tosses into a dataset folder of our format; returns its metadata.

    src_dir: the ContactNets `data/` folder (tosses_processed/, params_processed/).
    ids: toss ids to import (default all), all into the `test` split; or instead
    splits: {"train": [ids], "valid": [...], "test": [...]}.
    Every toss is read and checked before anything is written, so a bad file (DataError, one
    line naming it) leaves no output. Shards `<split>-00000.h5` of up to shard_size scenes are
    written atomically, metadata.json last. An existing non-empty out_dir is refused unless
    overwrite, which replaces only metadata.json and *.h5 files in it.
    """
    src_dir, out_dir = Path(src_dir), Path(out_dir)
    toss_dir = _toss_dir(src_dir)
    plan = _plan_splits(list_toss_ids(src_dir), ids, splits)
    check_output_folder(out_dir, overwrite, "use --overwrite (overwrite=True in Python) to replace it")
    consts = read_experiment(src_dir)
    # Read and check everything first: a bad toss must not leave half a dataset behind.
    scenes = _read_tosses(toss_dir, plan, consts, min_frames, allow_pickle, progress)
    _write_dataset(out_dir, scenes, consts, overwrite, shard_size)
    return json.loads((out_dir / METADATA_FILE).read_text())
