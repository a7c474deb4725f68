"""Errors of the map importers, and the lazy import of the optional ``roads`` extra.

Both are :class:`~mapcontainer.config.ConfigError` s: the command line prints them as one line and
exits 2, as it does for a bad configuration file.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from ..config import ConfigError

__all__ = ["EXTRA", "MapFileError", "MissingExtraError", "require"]

EXTRA = "roads"


class MapFileError(ConfigError):
    """A map file that cannot be read: missing, empty, not XML, not of the expected format, corrupt."""

    label = "cannot read the map"


class MissingExtraError(ConfigError):
    """A map format whose reader lives in the optional ``roads`` extra, which is not installed."""

    label = "missing optional dependency"


def require(module: str, what: str) -> ModuleType:
    """Import ``module`` (a package of the ``roads`` extra) or raise :class:`MissingExtraError` naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"{what} needs the Python package {module.split('.')[0]!r} ({exc}); install the optional extra: "
            f"pip install 'map-container[{EXTRA}]' (from a checkout: pip install -e '.[{EXTRA}]')"
        ) from None
