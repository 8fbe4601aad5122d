"""The TOML presets both tools read (configs/, shipped as the package rigid_gns_configs) and the
rules every config value follows: --set values read as TOML reads them, and one typing rule."""
from __future__ import annotations

import tomllib
from pathlib import Path

from plumbing.errors import ConfigError

DEFAULT_PRESET = "movi_a"   # the preset that marks a configs/ folder (datagen's scene defaults)


def config_dir() -> Path:
    """The presets (TOML): the checkout's configs/ folder, or, installed from a wheel, the same
    files shipped as the package `rigid_gns_configs` (pyproject.toml maps configs/ to it)."""
    checkout = Path(__file__).resolve().parent.parent / "configs"
    if (checkout / f"{DEFAULT_PRESET}.toml").is_file():
        return checkout
    from importlib.resources import files
    return Path(str(files("rigid_gns_configs")))


def preset_names() -> list[str]:
    return sorted(p.stem for p in config_dir().glob("*.toml"))


def config_path(path: str | Path) -> Path:
    """A TOML file, or a preset's name (gns_cpu, movi_a) looked up among the shipped presets;
    a path into a checkout's configs/ that is not there (installed package) falls back to the
    preset of that name."""
    p = Path(path)
    if p.is_file():
        return p
    if p.suffix in ("", ".toml") and (config_dir() / f"{p.stem}.toml").is_file() and (
            p.parent == Path(".") or p.parent.name == "configs"):
        return config_dir() / f"{p.stem}.toml"
    raise ConfigError(f"config file not found: {path} (presets: {', '.join(preset_names())})")


def load_toml(path: str | Path) -> dict:
    path = config_path(path)
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML ({e})") from None


def typed_value(key: str, value, default, where: str = ""):
    """value checked against the type of the default's (the preset's or the dataclass's): a
    string where a boolean belongs ("no" from a shell) must not be taken as true. Ints are
    accepted for floats. The one typing rule of datagen's and gns's configs."""
    expected = type(default)
    if expected is bool:
        ok = isinstance(value, bool)
    elif expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif expected is int:  # 12.0 from a float flag (--frame-rate) is the whole number 12
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif expected is list:
        ok = isinstance(value, list) and (not default or all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
            == all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in default))
    else:
        ok = isinstance(value, expected)
    if not ok:
        want = {bool: "true or false", float: "a number", int: "a whole number", list: "a list like the preset's",
                str: "a string"}.get(expected, expected.__name__)
        raise ConfigError(f"config key {key!r}{' ' + where if where else ''} must be {want}, got {value!r}")
    return value


def parse_value(text: str):
    """A --set value as TOML would read it (numbers, booleans, lists, quoted or bare strings);
    True/FALSE are booleans too, as a shell user would write them."""
    if text.strip().lower() in ("true", "false"):
        return text.strip().lower() == "true"
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
