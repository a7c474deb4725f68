"""Where configuration lives and how YAML files become validated pydantic models."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

__all__ = ["ConfigError", "config_dir", "config_error", "deep_merge", "load_yaml_model", "read_yaml", "validate_model"]

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration file is missing, not YAML, or does not validate (the message says where)."""


def config_dir() -> Path:
    """The configs/ directory: $MAPC_CONFIG_DIR, else the one beside the package (editable install)."""
    env = os.environ.get("MAPC_CONFIG_DIR")
    path = Path(env) if env else Path(__file__).resolve().parents[1] / "configs"
    if not path.is_dir():
        raise ConfigError(f"configuration directory {path} does not exist (set MAPC_CONFIG_DIR)")
    return path


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
        raise config_error(exc, source) from None


def config_error(exc: ValidationError, source: Path | str) -> ConfigError:
    """A pydantic validation error as a ConfigError: one line per field, naming ``source``."""
    lines = [f"{'.'.join(map(str, e['loc'])) or '<root>'}: {e['msg']}" for e in exc.errors()]
    return ConfigError(f"{source} is not a valid {exc.title}:\n  " + "\n  ".join(lines))
