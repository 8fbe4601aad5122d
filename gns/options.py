"""How a trained model is rolled out: one value, `RolloutOptions`, passed whole from the command
line, the Python API or a zoo card to the simulator, and recorded beside every score.

Options change how a rollout is computed, never the model: a zoo model's card holds the options
it was scored with, so `gns.load("movi_a")` and `gns eval --run movi_a` roll out as scored unless
told otherwise.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gns.config import ConfigError

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
