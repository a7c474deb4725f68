"""Where configuration lives and how YAML files become validated pydantic models."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

__all__ = [
    "BUILTIN_DIR",
    "ConfigError",
    "config_error",
    "deep_merge",
    "find_preset",
    "list_presets",
    "load_yaml_model",
    "preset_dirs",
    "read_yaml",
    "user_config_dirs",
    "validate_model",
]

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration file is missing, not YAML, or does not validate (the message says where)."""


BUILTIN_DIR = Path(str(resources.files(__package__) / "configs"))
"""The presets shipped with the package: ``scenarios/``, ``network/`` and ``sensors/`` (package data)."""


def user_config_dirs() -> list[Path]:
    """Directories whose presets override the built-in ones, first match wins: ``$MAPC_CONFIG_DIR``
    (``mapc --config-dir DIR`` sets it for every process it starts), then ``$XDG_CONFIG_HOME/mapcontainer``
    (default ``~/.config/mapcontainer``) when it exists. Each may hold any of the preset kinds."""
    dirs = []
    env = os.environ.get("MAPC_CONFIG_DIR")
    if env:
        path = Path(env).expanduser()
        if not path.is_dir():
            raise ConfigError(f"configuration directory {path} (MAPC_CONFIG_DIR) does not exist")
        dirs.append(path)
    xdg = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "mapcontainer"
    if xdg.is_dir():
        dirs.append(xdg)
    return dirs


def preset_dirs(kind: str, builtin: Path | None = None) -> list[Path]:
    """Where presets of ``kind`` are looked up, in order: the user's directories, then ``builtin``
    (default ``BUILTIN_DIR / kind``)."""
    return [d / kind for d in user_config_dirs()] + [builtin if builtin is not None else BUILTIN_DIR / kind]


def list_presets(kind: str, builtin: Path | None = None, suffix: str = ".yaml") -> dict[str, Path]:
    """Every preset of ``kind`` by name, each from the first directory that has it."""
    found: dict[str, Path] = {}
    for d in preset_dirs(kind, builtin):
        for f in sorted(d.glob(f"*{suffix}")) if d.is_dir() else []:
            found.setdefault(f.stem, f)
    return dict(sorted(found.items()))


def find_preset(kind: str, name: str, what: str, builtin: Path | None = None) -> Path:
    """The file of preset ``name``; a ConfigError naming the presets there are when there is none."""
    presets = list_presets(kind, builtin)
    if name not in presets:
        raise ConfigError(f"unknown {what} {name!r}; presets: {', '.join(presets) or 'none'}")
    return presets[name]


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """A new dict: ``override`` merged into ``base`` recursively (override wins)."""
    out = dict(base)
    for k, v in override.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path} is not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    except RecursionError:
        raise ConfigError(f"{path} is nested too deeply") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_yaml_model(model: type[M], path: Path, overrides: dict[str, Any] | None = None) -> M:
    """Load ``path`` as ``model`` (with optional overrides merged in); ConfigError on any problem."""
    data = read_yaml(path)
    if overrides:
        data = deep_merge(data, overrides)
    return validate_model(model, data, path)


def validate_model(model: type[M], data: dict[str, Any], source: Path | str) -> M:
    """``model.model_validate(data)``, turning validation errors into a ConfigError naming ``source``."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise config_error(exc, source, data) from None


def path_in_file(loc: tuple, data: Any) -> tuple:
    """A validation error's location as the file spells it: pydantic puts the tag of the union member it
    tried into the location (``map.procedural.lenght_m``), where the file says ``map.lenght_m``. The
    location is followed through ``data``; a part that is not there, before the last, is such a tag."""
    out, cur = [], data
    for i, part in enumerate(loc):
        if isinstance(cur, dict) and part in cur:
            cur = cur[part]
        elif isinstance(cur, list) and isinstance(part, int) and 0 <= part < len(cur):
            cur = cur[part]
        elif i < len(loc) - 1 and isinstance(cur, (dict, list)):
            continue  # a union member's tag, not in the file
        else:
            cur = None
        out.append(part)
    return tuple(out)


def config_error(exc: ValidationError, source: Path | str, data: Any = None) -> ConfigError:
    """A pydantic validation error as a ConfigError: one line per field, named as in ``data`` (what was
    validated, when given), naming ``source``."""
    locs = [e["loc"] if data is None else path_in_file(e["loc"], data) for e in exc.errors()]
    lines = [f"{'.'.join(map(str, loc)) or '<root>'}: {e['msg']}" for loc, e in zip(locs, exc.errors(), strict=True)]
    return ConfigError(f"{source} is not a valid {exc.title}:\n  " + "\n  ".join(lines))
