"""The model zoo and what is shipped: a few trained models named by purpose, each with a card
(gns/models/NAME.toml), and exported models (a checkpoint without its optimiser state).

A card says what the model is for, the data it was trained on, the one command that retrains
it, what that costs, its scores with the exact eval command, its speed and its limits, and the
rollout options it was scored with: `gns.load(NAME)` and `gns eval --run NAME` use those unless
told otherwise. Loaded only for a zoo name (gns.checkpoint.checkpoint_of), `gns models` and
`gns export`: a run folder or a checkpoint file is read without it.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import torch

from plumbing import atomic_file, check_writable, DataError
from gns.checkpoint import BETWEEN, CONTACT, CheckpointError, is_exported, read_checkpoint
from gns.spec import RolloutOptions


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


def _slim(ckpt: dict) -> dict:
    # an exported model's contact network goes along
    return {k: ckpt[k] for k in ("format", "step", "seed", "config", "spec", "model", "provenance", "train_seconds",
                                 CONTACT, BETWEEN) if k in ckpt}


def export_model(checkpoint_path: str | Path, out: str | Path, overwrite: bool = False,
                 contact: str | Path | None = None, between: str | Path | None = None) -> Path:
    """A checkpoint without the optimiser and random state (about half the size): enough to
    roll out and evaluate (load_model), not to resume training. With `contact` (another
    checkpoint of the same graphs) that model goes in as the contact network: it rolls out the
    objects in contact (LearnedSimulator.set_contact_model), checked by loading the two here.
    With `between` (a dataset recorded at the data's rate) a strided model gets its reader of the
    frames between its steps, fitted on that data's train split (gns.between).

    An existing `out` is replaced only with `overwrite` and only if it is itself an exported
    model: a full checkpoint (a run's latest.pt, say) or another file is never replaced."""
    ckpt = read_checkpoint(checkpoint_path)
    out = Path(out)
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; give a file name such as {out / 'model.pt'}")
    if out.exists():
        if not overwrite:
            raise DataError(f"{out} exists; pass --overwrite to replace an earlier exported model")
        try:
            old = read_checkpoint(out)
        except CheckpointError:
            old = None
        if old is None or not is_exported(old):
            raise DataError(f"{out} exists and is not an exported gns model; refusing to replace it")
    check_writable(out.parent, "output folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    slim = _slim(ckpt)
    if contact is not None:
        from gns.checkpoint import load_model
        slim[CONTACT] = _slim(read_checkpoint(contact))
        load_model(slim)   # CheckpointError now, not when it is used, if the two do not go together
    if between is not None:
        from gns.between import fit_on_data
        slim[BETWEEN] = fit_on_data(slim, between, progress=True)
    with atomic_file(out, mode=0o644) as tmp:  # an exported model is meant to be shared
        torch.save(slim, tmp)
    return out
