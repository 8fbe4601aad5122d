"""The model zoo: a few trained models named by purpose, each with a card (gns/models/NAME.toml).

A card says what the model is for, the data it was trained on, the one command that retrains
it, what that costs, its scores with the exact eval command, its speed and its limits, and the
rollout options it was scored with: `gns.load(NAME)` and `gns eval --run NAME` use those unless
told otherwise.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from gns.options import RolloutOptions

ZOO = Path(__file__).resolve().parent / "models"


class ZooError(LookupError):
    """A zoo name that is not there. One line for a user, naming the ones that are."""


@dataclass(frozen=True)
class Card:
    name: str
    file: Path            # the weights (several cards may share one file)
    options: RolloutOptions
    data: dict            # the card's TOML as read

    @property
    def purpose(self) -> str:
        return self.data.get("purpose", "")


def names() -> list[str]:
    return sorted(p.stem for p in ZOO.glob("*.toml"))


def card(name: str) -> Card:
    path = ZOO / f"{name}.toml"
    if not path.is_file():
        raise ZooError(f"no model {name!r} in the zoo; it has: {', '.join(names())} (gns models lists them)")
    with open(path, "rb") as f:
        data = tomllib.load(f)
    return Card(name, ZOO / data["file"], RolloutOptions.from_dict(data.get("rollout"), f"{path.name} [rollout]"),
                data)


def is_name(run) -> bool:
    """A bare word that is not a path on disk: meant as a zoo name."""
    run = Path(str(run))
    return not run.exists() and run.parent == Path(".") and run.suffix == ""


def default_options(run) -> RolloutOptions:
    """The options a run is rolled out with unless told otherwise: a zoo model's scored ones,
    else the defaults."""
    return card(str(run)).options if is_name(run) and (ZOO / f"{run}.toml").is_file() else RolloutOptions()
