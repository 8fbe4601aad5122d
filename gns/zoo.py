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
        raise ZooError(f"{name!r} is no run folder, checkpoint file or zoo model; the zoo has: "
                       f"{', '.join(names())} (`gns models` tells what each is for)")
    with open(path, "rb") as f:
        data = tomllib.load(f)
    return Card(name, ZOO / data["file"], RolloutOptions.from_dict(data.get("rollout"), f"{path.name} [rollout]"),
                data)


def is_name(run) -> bool:
    """A bare word that is not a path on disk: meant as a zoo name."""
    run = Path(str(run))
    return not run.exists() and run.parent == Path(".") and run.suffix == "" and str(run) != "."


def default_options(run) -> RolloutOptions:
    """The options a run is rolled out with unless told otherwise: a zoo model's scored ones,
    else the defaults."""
    return card(str(run)).options if is_name(run) and (ZOO / f"{run}.toml").is_file() else RolloutOptions()


def _score_line(s: dict) -> str:
    if "sides" in s:
        return f"on the right side: {s['sides']}"
    parts = [f"{s['position_error_pct']:g}% position / {s['rotation_error_deg']:g} deg rotation"]
    if "penetration_pct" in s:
        parts.append(f"{s['penetration_pct']:g}% penetration")
    return ", ".join(parts)


def format_list() -> str:
    """`gns models`: one block a model, its purpose and its first score."""
    lines = []
    for name in names():
        c = card(name)
        first = c.data.get("scores", [{}])[0]
        lines.append(f"{name}\n    {c.purpose}")
        if first:
            lines.append(f"    {_score_line(first)} on {first['test_set']}")
        opts = c.options.describe()
        lines.append(f"    rolled out with: {opts or 'the defaults'}\n")
    lines.append("`gns models NAME` prints a model's card; `gns eval --run NAME --data DIR` scores it, "
                 "`gns.load(NAME)` loads it, with the options above unless told otherwise.")
    return "\n".join(lines)


def format_card(name: str) -> str:
    """`gns models NAME`: the whole card, for a person."""
    c = card(name)
    d = c.data
    out = [f"# {name}", "", d.get("purpose", ""), "", f"Use: {d.get('use', '')}", "", "Limits:"]
    out += [f"- {x}" for x in d.get("limits", [])]
    data = d.get("data", {})
    out += ["", f"Data: {data.get('what', '')}", f"  made by: {data.get('command', '')}",
            f"  fingerprint: {data.get('fingerprint', '')}"]
    recipe = d.get("recipe", {})
    out += ["", f"Model: {recipe.get('model', '')}", f"Retrain: {recipe.get('command', '')}",
            f"  cost: {recipe.get('cost', '')}"]
    out += ["", f"Rollout options (the defaults of gns eval and gns.load): {c.options.describe() or 'none'}"]
    out += ["", "Scores:"]
    for s in d.get("scores", []):
        out.append(f"- {_score_line(s)} on {s['test_set']}")
        for key, label in (("data_command", "data"), ("eval_command", "eval"), ("note", "note")):
            if key in s:
                out.append(f"    {label}: {s[key]}")
    speed = d.get("speed", {})
    if speed:
        out += ["", f"Speed: {speed.get('summary', '')}", f"  measured by: {speed.get('command', '')}",
                f"  on: {speed.get('machine', '')}"]
    out.append(f"\nWeights: {c.file.name} ({c.file.stat().st_size / 1e6:.1f} MB)")
    return "\n".join(out)
