"""Scene configuration: a TOML preset (configs/movi_a.toml) plus command-line overrides.

The preset defines every key that exists; an override or user config naming an unknown key is
an error (a typo must not silently fall back to a default). New materials and sizes may be
added, as long as they carry the fields the built-in ones have.
"""
from __future__ import annotations

import copy
import difflib
import math
from pathlib import Path

from plumbing import config_dir, ConfigError, DEFAULT_PRESET, load_toml, parse_value, typed_value

# Tables whose entries a user may add to (each new entry must have the built-in entries' keys).
OPEN_TABLES = ("materials", "sizes")


def _unknown(key: str, known) -> ConfigError:
    close = difflib.get_close_matches(key.split(".")[-1], list(known), n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return ConfigError(f"unknown config key {key!r}{hint}")


def merge(base: dict, override: dict, prefix: str = "") -> dict:
    """Deep-merge override into a copy of base, refusing keys base does not define."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        key = f"{prefix}{k}"
        if prefix.rstrip(".") in OPEN_TABLES and k not in out:
            out[k] = copy.deepcopy(v)
            continue
        if k not in out:
            raise _unknown(key, out)
        if isinstance(out[k], dict):
            if not isinstance(v, dict):
                raise ConfigError(f"config key {key!r} is a table, got {v!r}")
            out[k] = merge(out[k], v, key + ".")
        else:
            out[k] = typed_value(key, v, out[k])
    return out


def apply_sets(cfg: dict, sets: list[str]) -> dict:
    for item in sets:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        dotted, value = item.split("=", 1)
        nested: dict = {}
        node = nested
        parts = dotted.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = parse_value(value.strip())
        cfg = merge(cfg, nested)
    return cfg


def load_config(path: str | Path | None = None, sets: list[str] | None = None) -> dict:
    cfg = load_toml(config_dir() / f"{DEFAULT_PRESET}.toml")
    if path is not None:
        cfg = merge(cfg, load_toml(path))
    cfg = apply_sets(cfg, sets or [])
    validate(cfg)
    return cfg


def parse_objects(spec) -> tuple[int, int]:
    """'1' -> (1, 1); '3-10' -> (3, 10)."""
    text = str(spec).strip()
    try:
        lo, hi = (text.split("-", 1) if "-" in text else (text, text))
        lo, hi = int(lo), int(hi)
    except ValueError:
        raise ConfigError(f"objects must be a count or a range like 3-10, got {spec!r}") from None
    if lo < 1 or hi < lo:
        raise ConfigError(f"objects range must satisfy 1 <= low <= high, got {spec!r}")
    return lo, hi


def _finite(key: str, value, low: float | None = None, high: float | None = None, strict_low: bool = False) -> None:
    values = value if isinstance(value, list) else [value]
    for x in values:
        x = float(x)
        bad = not math.isfinite(x) or (low is not None and (x <= low if strict_low else x < low)) or \
            (high is not None and x > high)
        if bad:
            rng = "" if low is None else f" {'>' if strict_low else '>='} {low:g}"
            rng += "" if high is None else f"{' and' if rng else ''} <= {high:g}"
            raise ConfigError(f"config key {key!r} must be finite{rng}, got {value!r}")


def validate(cfg: dict) -> None:
    """Check values, so a bad number fails here with its key rather than deep inside PyBullet."""
    sc, ph = cfg["scene"], cfg["physics"]
    # Physical values: a restitution above 1 gains energy, an infinite size fills shards with NaN.
    _finite("scene.frame_rate", sc["frame_rate"], 0, strict_low=True)
    _finite("physics.rate", ph["rate"], 0, strict_low=True)
    _finite("physics.gravity", ph["gravity"])
    _finite("floor.friction", cfg["floor"]["friction"], 0)
    _finite("floor.restitution", cfg["floor"]["restitution"], 0, 1)
    for k in ("low", "high", "velocity_low", "velocity_high"):
        _finite(f"spawn.{k}", cfg["spawn"][k])
    _finite("spawn.angular_velocity", cfg["spawn"]["angular_velocity"])
    for name, size in cfg["sizes"].items():
        _finite(f"sizes.{name}", size, 0, strict_low=True)
    for name, m in cfg["materials"].items():
        for k, low, high, strict in (("friction", 0, None, False), ("restitution", 0, 1, False),
                                     ("density", 0, None, True)):
            if k in m:
                _finite(f"materials.{name}.{k}", m[k], low, high, strict)
    if int(sc["frames"]) < 4:
        raise ConfigError(f"scene.frames must be >= 4 (a GNS window needs 4), got {sc['frames']}")
    if not float(sc["frame_rate"]) > 0:
        raise ConfigError(f"scene.frame_rate must be positive, got {sc['frame_rate']}")
    if not float(ph["rate"]) > 0:
        raise ConfigError(f"physics.rate must be positive, got {ph['rate']}")
    ratio = float(ph["rate"]) / float(sc["frame_rate"])
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ConfigError(f"physics.rate ({ph['rate']}) must be a whole multiple of scene.frame_rate ({sc['frame_rate']})")
    if len(ph["gravity"]) != 3:
        raise ConfigError("physics.gravity must have 3 components")
    if int(ph["solver_iterations"]) < 1:
        raise ConfigError("physics.solver_iterations must be >= 1")
    parse_objects(sc["objects"])
    from .shapes import parse_shapes
    try:
        parse_shapes(sc["shapes"])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    for name in sc["sizes"]:
        if name not in cfg["sizes"]:
            raise ConfigError(f"unknown size {name!r}; known sizes: {', '.join(cfg['sizes'])}")
        if not float(cfg["sizes"][name]) > 0:
            raise ConfigError(f"size {name!r} must be positive, got {cfg['sizes'][name]}")
    for name in sc["materials"]:
        if name not in cfg["materials"]:
            raise ConfigError(f"unknown material {name!r}; known materials: {', '.join(cfg['materials'])}")
    for name, m in cfg["materials"].items():
        for k in ("friction", "restitution", "density"):
            if k not in m:
                raise ConfigError(f"material {name!r} lacks {k!r}")
        if not float(m["density"]) > 0:
            raise ConfigError(f"material {name!r}: density must be positive")
        if float(m["friction"]) < 0 or not 0 <= float(m["restitution"]) <= 1:
            raise ConfigError(f"material {name!r}: need friction >= 0 and 0 <= restitution <= 1")
    sp = cfg["spawn"]
    for a, b in (("low", "high"), ("velocity_low", "velocity_high")):
        if len(sp[a]) != 3 or len(sp[b]) != 3 or any(float(x) > float(y) for x, y in zip(sp[a], sp[b])):
            raise ConfigError(f"spawn.{a} must be <= spawn.{b} componentwise (3 values each)")
    if cfg["floor"]["enabled"] and float(sp["low"][2]) < 0:
        raise ConfigError("spawn.low z must be >= 0 (above the floor)")
