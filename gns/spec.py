"""What a model was trained on, the typed model spec (`ModelSpec`) kept in every checkpoint, and
how it is rolled out (`RolloutOptions`, further down).

Training builds it from the data (gns.data.feature_spec), adds the meshes and the feature
layout, and saves it as a plain dict (`ModelSpec.to_dict`, the checkpoint's `spec`,
docs/model.md); everything that reads a checkpoint turns that dict back into a ModelSpec
(`ModelSpec.from_dict`), which accepts every checkpoint written so far: older ones lack
`collision_edges`, `collision_features` or `meshes`. The dict exists only at that boundary.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from gns.config import ConfigError


# keys every checkpoint written so far holds; older ones lack the others
REQUIRED = ("frame_rate", "gravity", "floor", "materials_vary", "shapes", "ranges", "node_features", "edge_features")


class SpecError(ValueError):
    """A model spec that cannot be read; one line (read_checkpoint adds the file)."""


@dataclass(frozen=True)
class Floor:
    """The ground plane z = `z`; friction and restitution as the data's metadata gave them."""

    z: float
    friction: float | None = None
    restitution: float | None = None

    @classmethod
    def from_dict(cls, d: Mapping) -> Floor:
        if not isinstance(d, Mapping):
            raise SpecError(f"floor must be a table or null, got {type(d).__name__}")
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if "z" not in d or unknown:
            raise SpecError(f"floor {dict(d)} needs 'z'" + (f" and has unknown {', '.join(map(repr, unknown))}"
                                                              if unknown else ""))
        try:
            return cls(z=float(d["z"]), **{k: None if d.get(k) is None else float(d[k])
                                           for k in ("friction", "restitution")})
        except (TypeError, ValueError):
            raise SpecError(f"floor {dict(d)}: values must be numbers") from None

    def to_dict(self) -> dict:
        """As in the data's metadata.json: sorted keys, absent values left out."""
        return {k: v for k, v in (("friction", self.friction), ("restitution", self.restitution), ("z", self.z))
                if v is not None}


@dataclass(frozen=True, kw_only=True)
class ModelSpec:
    """Physics constants, shapes, value ranges, meshes and feature layout of a model's training data.

    frame_rate and gravity are None only for a simulator built without them (tests and
    benchmarks: no sleeping, no free flight); every checkpoint holds both. node_features,
    edge_features and collision_features (the layout, gns.network) are set by training
    (None before: a spec of data). meshes {name: (vertices (V, 3) float64, faces (F, 3) int64)}
    tensors; None in checkpoints written before they were kept."""

    frame_rate: float | None = None                     # model steps per second
    gravity: tuple[float, float, float] | None = None   # scene units / s^2
    floor: Floor | None = None
    materials_vary: bool = False                        # friction and restitution are node inputs
    collision_edges: bool = False                       # some training scene held several objects
    shapes: tuple[str, ...] = ()                        # shapes seen in training, sorted
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)  # (min, max) seen in training
    meshes: dict[str, tuple[torch.Tensor, torch.Tensor]] | None = field(default=None, compare=False, repr=False)
    node_features: tuple[str, ...] | None = None
    edge_features: tuple[str, ...] | None = None
    collision_features: tuple[str, ...] | None = None

    @property
    def floor_z(self) -> float | None:
        return None if self.floor is None else self.floor.z

    @property
    def gravity_step(self) -> float | None:
        """|g| dt^2, in scene units per frame (what Sleep's threshold is made of)."""
        if self.gravity is None or self.frame_rate is None:
            return None
        return float(torch.tensor(self.gravity).norm()) / self.frame_rate ** 2

    @property
    def gravity_per_frame(self) -> torch.Tensor | None:
        """g dt^2 as a float64 (3,) vector: the centre's second difference in free flight."""
        if self.gravity is None or self.frame_rate is None:
            return None
        return torch.tensor(self.gravity, dtype=torch.float64) / self.frame_rate ** 2

    @classmethod
    def from_dict(cls, d: Mapping, partial: bool = False) -> ModelSpec:
        """A checkpoint's `spec`. Raises SpecError (one line) on a missing key, an unknown key
        or a value of the wrong kind. partial: only materials_vary is required (the few keys a
        benchmark builds an untrained simulator from)."""
        if not isinstance(d, Mapping):
            raise SpecError(f"model spec must be a table, got {type(d).__name__}")
        # a checkpoint's floor may be null (no floor), nothing else it must hold
        missing = [k for k in (("materials_vary",) if partial else REQUIRED)
                   if k not in d or (d[k] is None and k != "floor")]
        if missing:
            raise SpecError(f"model spec lacks {', '.join(map(repr, missing))}")
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise SpecError(f"model spec has unknown key(s) {', '.join(map(repr, unknown))}")
        out = {}
        for key, read in _READERS.items():
            if d.get(key) is None:
                continue
            try:
                out[key] = read(d[key])
            except SpecError:
                raise
            except (TypeError, ValueError, KeyError, IndexError, AttributeError):
                raise SpecError(f"model spec: {key} is not {_KINDS[key]} (got {str(d[key])[:80]})") from None
        return cls(**out)

    def to_dict(self) -> dict:
        """What checkpoints store: plain lists, floats and strings (meshes as tensors), in the
        order training has always written them; keys whose value is None left out."""
        out = {"frame_rate": self.frame_rate, "gravity": None if self.gravity is None else list(self.gravity),
               "floor": None if self.floor is None else self.floor.to_dict(),
               "materials_vary": self.materials_vary, "collision_edges": self.collision_edges,
               "shapes": list(self.shapes), "ranges": {k: [lo, hi] for k, (lo, hi) in self.ranges.items()}}
        if self.frame_rate is None:
            del out["frame_rate"]
        if self.gravity is None:
            del out["gravity"]
        if self.meshes is not None:
            out["meshes"] = {name: {"vertices": v, "faces": f} for name, (v, f) in self.meshes.items()}
        for key in ("node_features", "edge_features", "collision_features"):
            if getattr(self, key) is not None:
                out[key] = list(getattr(self, key))
        return out


def _gravity(g) -> tuple[float, float, float]:
    out = tuple(float(x) for x in g)
    if len(out) != 3:
        raise ValueError
    return out


def _pair(v) -> tuple[float, float]:
    lo, hi = v
    return float(lo), float(hi)


def _names(v) -> tuple[str, ...]:
    if isinstance(v, str) or not all(isinstance(x, str) for x in v):
        raise TypeError
    return tuple(v)


def _bool(v) -> bool:
    if not isinstance(v, bool):
        raise TypeError
    return v


def _rate(v) -> float:
    if isinstance(v, (str, bool)) or not float(v) > 0:
        raise ValueError
    return float(v)


_READERS = {
    "frame_rate": _rate,
    "gravity": _gravity,
    "floor": Floor.from_dict,
    "materials_vary": _bool,
    "collision_edges": _bool,
    "shapes": _names,
    "ranges": lambda r: {str(k): _pair(v) for k, v in r.items()},
    "meshes": lambda m: {str(name): (x["vertices"], x["faces"]) for name, x in m.items()},
    "node_features": _names,
    "edge_features": _names,
    "collision_features": _names,
}
_KINDS = {"frame_rate": "a number > 0", "gravity": "3 numbers", "materials_vary": "true or false",
          "collision_edges": "true or false", "shapes": "a list of names",
          "ranges": "a table of [min, max] pairs", "meshes": "a table of {vertices, faces}",
          "node_features": "a list of names", "edge_features": "a list of names",
          "collision_features": "a list of names"}


# A value may exceed the trained range by this fraction of the range's magnitude before a
# warning: test data drawn from the training distribution rarely matches its extremes exactly.
SLACK = 0.1

UNITS = {"speed": "units/s", "angular_speed": "rad/s", "height": "units", "scale": "", "friction": "",
         "restitution": ""}


def outside_training(trained: ModelSpec, data: ModelSpec) -> list[str]:
    """Warnings (one line each) for `data` (a gns.data.feature_spec of the input scenes)
    falling outside `trained` (the checkpoint's spec)."""
    out = []
    if not np.isclose(trained.frame_rate, data.frame_rate, rtol=1e-6):
        out.append(f"frame rate {data.frame_rate:g} fps, the model was trained at {trained.frame_rate:g} fps "
                   "(it predicts one frame ahead: resample the data)")
    if not np.allclose(trained.gravity, data.gravity, rtol=1e-6):
        out.append(f"gravity {list(data.gravity)}, trained with {list(trained.gravity)}")
    if (trained.floor is None) != (data.floor is None):
        out.append("the model was trained " + ("without" if trained.floor is None else "with") + " a floor")
    unseen = sorted(set(data.shapes) - set(trained.shapes))
    if unseen:
        out.append(f"shape(s) {', '.join(unseen)} not seen in training ({', '.join(trained.shapes)})")
    for key, (lo, hi) in trained.ranges.items():
        if key not in data.ranges:
            continue
        dlo, dhi = data.ranges[key]
        slack = SLACK * max(abs(lo), abs(hi), 1e-9)
        if dlo < lo - slack or dhi > hi + slack:
            unit = f" {UNITS.get(key, '')}".rstrip()
            out.append(f"{key.replace('_', ' ')} {dlo:.3g} to {dhi:.3g}{unit} is outside the trained "
                       f"{lo:.3g} to {hi:.3g}{unit}")
    return out


# How a trained model is rolled out: one value, `RolloutOptions`, passed whole from the command
# line, the Python API or a zoo card to the simulator, and recorded beside every score.
#
# Options change how a rollout is computed, never the model: a zoo model's card holds the options
# it was scored with, so `gns.load("movi_a")` and `gns eval --run movi_a` roll out as scored unless
# told otherwise.


SYMMETRIES = ("none", "d1", "c2", "d2", "c4", "d4")
AUTOCASTS = ("none", "bf16", "auto")


class OptionsError(ConfigError, ValueError):
    """A rollout option that cannot be used. One line for a user."""


@dataclass(frozen=True)
class RolloutOptions:
    # the Euler update is followed by fitting each object's rest shape (the paper's shape matching)
    shape_matching: bool = True
    # average each step over a group of the floor's symmetries (gns.symmetry): d1 two network calls
    # a step, d2 four, d4 eight; "none" one
    symmetrize: str = "none"
    # average over each object's equivalent body frames as well (24x for a cube)
    body_frames: bool = False
    # objects out of reach of the floor and of each other move by the exact inertial update
    free_flight: bool = False
    # with free_flight: also let fly objects nearer the floor than the floor clip when no vertex can
    # reach it within the step (None: only those beyond the floor clip)
    free_clearance: float | None = None
    # keep objects lying still on the floor asleep (Bullet-style deactivation)
    sleep: bool = False
    sleep_fraction: float = 0.1
    # after each step, translate objects of a scene out of each other (gns.contacts.separation)
    keep_apart: bool = False
    # the network under bfloat16 autocast; "auto" only where the CPU measures it faster
    autocast: str = "none"
    # torch.compile with inductor's freezing
    compile: bool = False
    # objects rolled out together
    batch: int = 1024
    # other models whose predictions each step averages with this one's
    ensemble: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self):
        sym = self.symmetrize
        if sym is True:
            sym = "d2"
        elif sym is False or sym is None:
            sym = "none"
        object.__setattr__(self, "symmetrize", sym)
        object.__setattr__(self, "ensemble", tuple(str(e) for e in self.ensemble))
        if self.symmetrize not in SYMMETRIES:
            raise OptionsError(f"symmetrize: unknown symmetry group {self.symmetrize!r}; known: {', '.join(SYMMETRIES)}")
        if self.autocast not in AUTOCASTS:
            raise OptionsError(f"autocast={self.autocast!r}: one of {', '.join(AUTOCASTS)}")
        if self.free_clearance is not None and not self.free_clearance >= 0:
            raise OptionsError(f"free flight clearance must be a height >= 0 above the floor, not {self.free_clearance}")
        if not isinstance(self.batch, int) or self.batch < 1:
            raise OptionsError(f"batch={self.batch!r}: a whole number >= 1")
        if not 0 < self.sleep_fraction:
            raise OptionsError(f"sleep_fraction={self.sleep_fraction!r}: a number > 0")

    @property
    def symmetry_group(self) -> str | None:
        return None if self.symmetrize == "none" else self.symmetrize

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["ensemble"] = list(self.ensemble)
        return out

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "rollout options") -> "RolloutOptions":
        d = dict(d or {})
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise OptionsError(f"{where}: unknown option {unknown[0]!r}; known: {', '.join(sorted(known))}")
        return cls(**d)

    def replace(self, **changes) -> "RolloutOptions":
        """These options with `changes`; a change of None keeps the value (an unset flag)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def describe(self) -> str:
        """The options that differ from the defaults, as `gns eval` flags."""
        base = RolloutOptions()
        parts = []
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v == getattr(base, f.name):
                continue
            flag = "--" + f.name.replace("_", "-")
            if f.name == "shape_matching":
                parts.append("--no-shape-matching")
            elif f.name == "ensemble":
                parts.extend(f"--ensemble {e}" for e in v)
            elif isinstance(v, bool):
                parts.append(flag)
            else:
                parts.append(f"{flag} {v}")
        return " ".join(parts)
