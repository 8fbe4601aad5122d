"""The dataset format: HDF5 shards plus `metadata.json`. The contract is docs/data_format.md.

This module is the only place that knows the layout on disk. The generator writes through
`write_shard`/`write_metadata`; the GNS trainer, rollouts and `datagen inspect` read through
`Dataset`. Every write goes to a temporary file first and is renamed when complete, so a
crash or a full disk never leaves a half-written shard under its final name. The quaternion
conversions of the format's order (w x y z) are at the end.
"""
from __future__ import annotations

import errno
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np
from scipy.spatial.transform import Rotation

from plumbing import atomic_file, DataError
from plumbing import file_sha256, fingerprint, provenance

FORMAT_VERSION = 1
METADATA_FILE = "metadata.json"
QUATERNION_ORDER = "wxyz"
SPLITS = ("train", "valid", "test")
# mkstemp makes owner-only files; a dataset is meant to be shared.
SHARED = 0o644

SCENE_ARRAYS = ("positions", "quaternions", "velocities", "angular_velocities")
OBJECT_ARRAYS = ("scale", "mass", "friction", "restitution")
OBJECT_STRINGS = ("shape", "material")


@dataclass
class Scene:
    """One recorded scene: T frames of N objects. Poses are the objects' centre of mass."""

    positions: np.ndarray           # (T, N, 3) float64, world frame
    quaternions: np.ndarray         # (T, N, 4) float64, w x y z, body -> world
    velocities: np.ndarray          # (T, N, 3) float64, world frame
    angular_velocities: np.ndarray  # (T, N, 3) float64, world frame
    shape: list[str]                # (N,) asset names, keys of Dataset.meshes
    material: list[str]             # (N,)
    scale: np.ndarray               # (N,) uniform scale of the unit asset
    mass: np.ndarray                # (N,)
    friction: np.ndarray            # (N,)
    restitution: np.ndarray         # (N,)
    attrs: dict = field(default_factory=dict)  # scene_id, seed, and anything the source adds

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def num_objects(self) -> int:
        return self.positions.shape[1]

    def every(self, stride: int, phase: int = 0) -> "Scene":
        """Every `stride`-th frame from frame `phase`: the scene as if recorded at 1/stride the rate."""
        if stride == 1 and phase == 0:
            return self
        return Scene(*(getattr(self, k)[phase::stride] for k in SCENE_ARRAYS), self.shape, self.material,
                     self.scale, self.mass, self.friction, self.restitution,
                     {**self.attrs, "frame_stride": stride, "frame_phase": phase})


def shard_name(split: str, index: int) -> str:
    """The file name of a split's index-th shard: the one naming rule of the format."""
    return f"{split}-{index:05d}.h5"


def dataset_files(root: str | Path) -> list[Path]:
    """The files of a dataset folder that the tools write (metadata, shards named by
    shard_name, and their temporary files): what an overwrite may delete, and nothing else."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_file() and (_own(p.name) or own_temporary(p.name)))


def _own(name: str) -> bool:
    """Whether a file name is the metadata's or one that shard_name gives."""
    split, _, rest = name.partition("-")
    index = rest.removesuffix(".h5")
    return name == METADATA_FILE or (split in SPLITS and index.isdigit() and shard_name(split, int(index)) == name)


def temporary_target(name: str) -> str | None:
    """The file an atomic_file temporary `.<name>.<random>.tmp` becomes, None for another name."""
    return name[1:-len(".tmp")].rpartition(".")[0] if name.startswith(".") and name.endswith(".tmp") else None


def own_temporary(name: str) -> bool:
    """Whether a file name is atomic_file's temporary of an _own name."""
    target = temporary_target(name)
    return target is not None and _own(target)


def clear_dataset(root: str | Path) -> None:
    """Delete a dataset's own files (metadata first, so an interrupted clear never looks like a
    complete dataset); a user's other files in the folder stay."""
    files = dataset_files(root)
    for p in sorted(files, key=lambda p: p.name != METADATA_FILE):
        p.unlink(missing_ok=True)


def write_shard(path: str | Path, scenes: list[Scene], meshes: dict[str, tuple[np.ndarray, np.ndarray]],
                attrs: dict | None = None) -> None:
    """Write scenes and the rest meshes into one HDF5 shard, atomically.

    Scenes are packed into a few tables (docs/data_format.md) rather than one HDF5 group per
    scene: a group per scene costs ~2 ms of HDF5 bookkeeping to write and to read, as much
    as simulating a scene, while the packed tables cost the same for 1 or 1000 scenes.
    """
    path = Path(path)
    try:
        image = shard_image(scenes, meshes, attrs, path.name)
    except OSError as e:
        raise write_error(path, e) from None
    write_shard_image(path, image)


def write_shard_image(path: str | Path, image: bytes) -> None:
    """Write a shard built by shard_image atomically (temporary file, then rename)."""
    path = Path(path)
    try:
        with atomic_file(path, mode=SHARED) as tmp, open(tmp, "wb") as out:
            out.write(image)
    except OSError as e:
        raise write_error(path, e) from None


def shard_image(scenes: list[Scene], meshes: dict[str, tuple[np.ndarray, np.ndarray]], attrs: dict | None = None,
                name: str = "shard.h5") -> bytes:
    """The bytes of a shard file, built in memory: the same bytes wherever they are built, so a
    remote worker (the ray backend) can build a shard and the driver write it."""
    frames = np.array([sc.num_frames for sc in scenes], np.int64)
    objects = np.array([sc.num_objects for sc in scenes], np.int64)
    rows = frames * objects
    # Built in memory, then written with plain file I/O: a full disk is then one clean OSError,
    # where HDF5 writing to a full disk prints hundreds of lines and can crash the process.
    with h5py.File(name, "w", driver="core", backing_store=False) as f:
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["quaternion_order"] = QUATERNION_ORDER
        f.attrs["num_scenes"] = len(scenes)
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        # Every shard carries all the dataset's meshes so it can be read on its own.
        mg = f.create_group("meshes")
        for mesh_name in sorted(meshes):
            verts, faces = meshes[mesh_name]
            g = mg.create_group(mesh_name)
            g.create_dataset("vertices", data=np.asarray(verts, np.float64))
            g.create_dataset("faces", data=np.asarray(faces, np.int32))
        sg = f.create_group("scenes")
        sg.create_dataset("num_frames", data=frames)
        sg.create_dataset("num_objects", data=objects)
        sg.create_dataset("object_start", data=np.concatenate([[0], np.cumsum(objects)[:-1]]).astype(np.int64))
        sg.create_dataset("state_start", data=np.concatenate([[0], np.cumsum(rows)[:-1]]).astype(np.int64))
        sg.create_dataset("attrs", data=np.array([json.dumps(sc.attrs, sort_keys=True) for sc in scenes],
                                                 dtype=h5py.string_dtype()))
        st = f.create_group("states")
        for k in SCENE_ARRAYS:
            width = 4 if k == "quaternions" else 3
            st.create_dataset(k, data=np.concatenate(
                [np.asarray(getattr(sc, k), np.float64).reshape(-1, width) for sc in scenes]))
        og = f.create_group("objects")
        for k in OBJECT_ARRAYS:
            og.create_dataset(k, data=np.concatenate([np.asarray(getattr(sc, k), np.float64) for sc in scenes]))
        for k in OBJECT_STRINGS:
            og.create_dataset(k, data=np.array([x for sc in scenes for x in getattr(sc, k)], dtype=h5py.string_dtype()))
        f.flush()
        return f.id.get_file_image()


def write_error(path: Path, e: OSError) -> DataError:
    """One line for a failed write (a full disk above all); the partial file is already removed."""
    if e.errno == errno.ENOSPC:
        return DataError(f"No space left on device writing {path}; the partial file was removed "
                         "(free some space and rerun with --resume)")
    return DataError(f"cannot write {path}: {e.strerror or e}")


def shard_checksums(root: str | Path, splits: dict) -> dict[str, str]:
    """sha256 of every shard a `splits` table lists, by file name."""
    root = Path(root)
    return {name: file_sha256(root / name) for info in splits.values() for name in info["shards"]}


def write_metadata(root: str | Path, meta: dict) -> dict:
    """Write metadata.json atomically, adding `provenance` (versions, code commit) and, unless
    `complete` is false, `checksums` of the listed shards and the dataset `fingerprint`
    (docs/data_format.md). So every writer of a dataset records them, and a copied metadata
    (gns rollout starts from its source's) never carries another dataset's. Returns what was written."""
    root = Path(root)
    meta = {k: v for k, v in meta.items() if k not in ("provenance", "checksums", "fingerprint")}
    meta = {"format_version": FORMAT_VERSION, **meta, "provenance": provenance()}
    if meta.get("complete") is not False:
        meta["checksums"] = shard_checksums(root, meta["splits"])
        meta["fingerprint"] = fingerprint(meta, meta["checksums"])
    with atomic_file(root / METADATA_FILE, mode=SHARED) as tmp:
        tmp.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return meta


def _strings(a) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in a]


def read_shard(path: str | Path) -> tuple[list[Scene], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """All scenes and meshes of one shard. Raises DataError with one line on any problem."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"missing shard: {path}")
    try:
        with h5py.File(path, "r") as f:
            version = int(f.attrs.get("format_version", -1))
            if version != FORMAT_VERSION:
                raise DataError(f"{path}: format version {version}, this reader reads {FORMAT_VERSION}")
            order = f.attrs.get("quaternion_order", "")
            if order != QUATERNION_ORDER:
                raise DataError(f"{path}: quaternion order {order!r}, expected {QUATERNION_ORDER!r}")
            meshes = {name: (g["vertices"][()], g["faces"][()]) for name, g in f["meshes"].items()}
            sg, st, og = f["scenes"], f["states"], f["objects"]
            frames, objects = sg["num_frames"][()], sg["num_objects"][()]
            o0s, s0s = sg["object_start"][()], sg["state_start"][()]
            scene_attrs = _strings(sg["attrs"][()])
            states = {k: st[k][()] for k in SCENE_ARRAYS}
            per_object = {k: og[k][()] for k in OBJECT_ARRAYS}
            names = {k: _strings(og[k][()]) for k in OBJECT_STRINGS}
            total_rows = int((frames * objects).sum())
            if any(len(a) != total_rows for a in states.values()) or \
                    any(len(a) != int(objects.sum()) for a in (*per_object.values(), *names.values())):
                raise DataError(f"{path}: table lengths disagree with the scene index (truncated or corrupt)")
            scenes = []
            for T, N, o0, s0, a in zip(frames, objects, o0s, s0s, scene_attrs):
                T, N, o0, s0 = int(T), int(N), int(o0), int(s0)
                arrays = {k: v[s0:s0 + T * N].reshape(T, N, -1) for k, v in states.items()}
                objs = {k: v[o0:o0 + N] for k, v in per_object.items()}
                strs = {k: v[o0:o0 + N] for k, v in names.items()}
                scenes.append(Scene(**arrays, **objs, **strs, attrs=json.loads(a)))
            if len(scenes) != int(f.attrs.get("num_scenes", len(scenes))):
                raise DataError(f"{path}: holds {len(scenes)} scenes, header says {f.attrs['num_scenes']}")
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise DataError(f"unreadable or truncated shard {path}: {e}") from None
    return scenes, meshes


# What every reader of a dataset relies on (docs/data_format.md).
REQUIRED_META = ("frame_rate", "gravity", "floor", "splits")


class Dataset:
    """A dataset folder: `metadata.json` plus the shards it lists, per split.

    `stride` k reads every k-th recorded frame, so the dataset looks recorded at frame_rate / k:
    a model's time step is a choice made when reading, not when simulating (finer data serves
    every coarser step).
    """

    def __init__(self, root: str | Path, stride: int = 1):
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise DataError(f"frame stride must be a whole number >= 1, got {stride!r}")
        self.stride = stride
        self.root = Path(root)
        meta_path = self.root / METADATA_FILE
        if not self.root.is_dir():
            raise DataError(f"not a dataset folder (does not exist): {self.root}")
        if not meta_path.exists():
            raise DataError(f"not a dataset folder (no {METADATA_FILE}): {self.root}")
        try:
            self.meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise DataError(f"{meta_path}: invalid JSON ({e})") from None
        if not isinstance(self.meta, dict):
            raise DataError(f"{meta_path}: not a JSON object (got {type(self.meta).__name__})")
        version = self.meta.get("format_version")
        if version != FORMAT_VERSION:
            raise DataError(f"{meta_path}: format version {version}, this reader reads {FORMAT_VERSION}")
        if self.meta.get("complete") is False:
            raise DataError(f"{self.root}: incomplete dataset (generation was interrupted); "
                            "finish it with `datagen toss ... --resume`")
        missing = [k for k in REQUIRED_META if k not in self.meta]
        if missing:
            raise DataError(f"{meta_path}: lacks {', '.join(repr(k) for k in missing)}")
        splits = self.meta["splits"]
        if not isinstance(splits, dict) or not all(
                isinstance(v, dict) and isinstance(v.get("shards"), list) and isinstance(v.get("num_scenes"), int)
                for v in splits.values()):
            raise DataError(f"{meta_path}: 'splits' must map each split to {{'num_scenes': int, 'shards': [names]}}")
        self._meshes: dict | None = None

    # Scene-level physical constants, so the trainer never reads the generator's config.
    @property
    def frame_rate(self) -> float:
        """Frames per second as read (the recorded rate / stride)."""
        return float(self.meta["frame_rate"]) / self.stride

    @property
    def dt(self) -> float:
        return 1.0 / self.frame_rate

    @property
    def gravity(self) -> np.ndarray:
        return np.asarray(self.meta["gravity"], np.float64)

    @property
    def floor(self) -> dict | None:
        return self.meta.get("floor")

    @property
    def splits(self) -> list[str]:
        return [s for s in SPLITS if self.meta["splits"].get(s, {}).get("num_scenes", 0) > 0]

    def num_scenes(self, split: str) -> int:
        return int(self.meta["splits"].get(split, {}).get("num_scenes", 0))

    def shard_paths(self, split: str) -> list[Path]:
        if split not in self.meta["splits"]:
            raise DataError(f"{self.root}: no split {split!r}; it has {', '.join(self.meta['splits'])}")
        return [self.root / name for name in self.meta["splits"][split]["shards"]]

    def scenes(self, split: str) -> Iterator[Scene]:
        for p in self.shard_paths(split):
            scenes, meshes = read_shard(p)
            self._remember(meshes)
            yield from (sc.every(self.stride) for sc in scenes)

    def load(self, split: str, limit: int | None = None) -> list[Scene]:
        out = []
        for sc in self.scenes(split):
            if limit is not None and len(out) >= limit:
                break
            out.append(sc)
        return out

    @property
    def meshes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Rest meshes by shape name, read from the shards (the simulated shapes, exactly)."""
        if self._meshes is None:
            split = self.splits[0] if self.splits else None
            if split is None:
                raise DataError(f"{self.root}: the dataset holds no scenes")
            _, meshes = read_shard(self.shard_paths(split)[0])
            self._remember(meshes)
        return self._meshes

    def _remember(self, meshes):
        if self._meshes is None:
            self._meshes = {}
        self._meshes.update(meshes)

    @property
    def fingerprint(self) -> str:
        """The dataset fingerprint (docs/data_format.md): the one metadata.json records, or, for a
        dataset written before fingerprints existed, computed from its metadata and shards."""
        recorded = self.meta.get("fingerprint")
        if isinstance(recorded, str):
            return recorded
        return fingerprint(self.meta, shard_checksums(self.root, self.meta["splits"]))

    @property
    def materials_vary(self) -> bool:
        """Whether friction or restitution differ between objects: then they are node features."""
        return bool(self.meta.get("materials_vary", False))


# Quaternions in the dataset's order (w x y z, body -> world) and scipy's Rotation, which holds
# them x y z w: the conversions, and the sign choice that keeps a trajectory on one cover.


def wxyz(q_xyzw) -> np.ndarray:
    """(..., 4) x y z w (scipy, PyBullet) -> w x y z."""
    return np.asarray(q_xyzw)[..., [3, 0, 1, 2]]


def xyzw(q_wxyz) -> np.ndarray:
    """(..., 4) w x y z -> x y z w (scipy, PyBullet)."""
    return np.asarray(q_wxyz)[..., [1, 2, 3, 0]]


def rotation(q_wxyz) -> Rotation:
    """scipy Rotation(s) of w x y z quaternions (..., 4)."""
    return Rotation.from_quat(xyzw(q_wxyz))


def continuous(quat: np.ndarray) -> np.ndarray:
    """A copy of quaternions (T, ..., 4) with signs flipped so consecutive frames lie on the same
    cover: q and -q are one rotation, and finite differences or interpolation of quaternions
    must not see the jump between them."""
    flips = np.where(np.sum(quat[1:] * quat[:-1], axis=-1) < 0, -1.0, 1.0)
    quat = quat.copy()
    quat[1:] *= np.cumprod(flips, axis=0)[..., None]
    return quat
