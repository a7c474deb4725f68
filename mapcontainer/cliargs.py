"""The command line's argument types and parser: values checked before any work is done, and a
misspelled option answered with the usage of the subcommand it was given to and the nearest option."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import math
import os
from pathlib import Path

__all__ = [
    "Parser",
    "config_dir_arg",
    "fleet_name",
    "fleet_sizes",
    "non_negative_int",
    "non_negative_seconds",
    "origin_arg",
    "output_dir",
    "output_file",
    "positive_days",
    "positive_float",
    "positive_int",
    "seconds",
    "vehicle_ids",
]


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose subcommands (made by ``add_subparsers``, which uses the parent's class) know
    themselves: an option no subcommand takes is reported by the innermost subcommand chosen, with its
    usage, and the closest of its options (``--bound``: did you mean ``--bounds``?)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.set_defaults(_parser=self)

    def parse_args(self, args=None, namespace=None):
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            owner = getattr(ns, "_parser", self)
            owner.error(owner.unrecognized(extras))
        return ns

    def unrecognized(self, extras: list[str]) -> str:
        options = [o for a in self._actions for o in a.option_strings]
        msg = f"unrecognized arguments: {' '.join(extras)}"
        for extra in extras:
            if extra.startswith("-"):
                close = difflib.get_close_matches(extra.split("=", 1)[0], options, n=1, cutoff=0.6)
                if close:
                    return f"{msg} (did you mean {close[0]}?)"
        return msg


def bounded(parse: type, low: float, strict: bool, unit: str = ""):
    """An argparse type: ``parse(text)``, finite (inf or nan used to fail deep inside a run) and
    above ``low`` (``strict``) or at least ``low``."""

    def check(text: str):
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not {'an integer' if parse is int else 'a number'}: {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be finite, got {text}")
        if value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"must be {'>' if strict else '>='} {low:g}{unit}, got {text}")
        return value

    return check


seconds = bounded(float, 0, strict=True, unit=" s")
non_negative_seconds = bounded(float, 0, strict=False, unit=" s")
positive_int = bounded(int, 1, strict=False)
non_negative_int = bounded(int, 0, strict=False)
positive_days = bounded(float, 0, strict=True, unit=" days")
positive_float = bounded(float, 0, strict=True)


def fleet_sizes(text: str) -> list[int]:
    """``2,4,8``: two or more distinct fleet sizes, each at least 1."""
    try:
        sizes = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of integers: {text!r}") from None
    if len(set(sizes)) < 2 or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"need two or more different sizes, each >= 1, got {text!r}")
    return sizes


def _ids(text: str, what: str) -> list[str]:
    from schemas.topics import is_chunk

    ids = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in ids if not is_chunk(v) or v == "ca"]
    if not ids or bad:
        raise argparse.ArgumentTypeError(f"not a list of {what} ids: {', '.join(map(repr, bad)) or repr(text)}")
    if len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"a {what} id is repeated in {text!r}")
    return ids


def vehicle_ids(text: str) -> list[str]:
    """``cv0,cv1,...``: distinct ids (letters, digits, '_' or '-'), none of them ``ca``."""
    return _ids(text, "vehicle")


def service_ids(text: str) -> list[str]:
    """``world,host,...``: distinct service ids, as :func:`vehicle_ids`."""
    return _ids(text, "service")


def fleet_name(text: str) -> str:
    """A fleet name: one key chunk of the topics (letters, digits, '_' or '-')."""
    from schemas.topics import is_chunk

    if not is_chunk(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a fleet name (letters, digits, '_' or '-')")
    return text


def config_dir_arg(value: str) -> Path:
    """``--config-dir``: an existing directory, absolute (the services the launcher starts inherit it)."""
    path = Path(value).expanduser().resolve()
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{value} is not a directory")
    return path


def output_dir(value: str) -> Path:
    """An ``--out`` directory, absolute (fleets run elsewhere write into it), checked before any work
    is done: a file of that name, or a place where no directory can be made, used to fail only after
    the whole run, losing it. A directory that does not exist yet is made and removed again (a probe:
    a command refused later leaves nothing behind)."""
    path = Path(value).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{value} exists and is not a directory")
    missing = [p for p in (path, *path.parents) if not p.exists()]  # deepest first
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(13, "Permission denied")
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot write into {value}: {exc.strerror}") from None
    finally:
        for d in missing:
            with contextlib.suppress(OSError):
                d.rmdir()
    return path


def origin_arg(text: str):
    """``LAT,LON[,ALT]`` in degrees (WGS84) and metres: the geodetic position of the map origin."""
    from .hdmap.io import MapOrigin

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not LAT,LON[,ALT]: {text!r}") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"not LAT,LON[,ALT]: {text!r}")
    if not (-90 <= values[0] <= 90 and -180 <= values[1] <= 180):
        raise argparse.ArgumentTypeError(f"latitude or longitude out of range: {text!r}")
    return MapOrigin(*values)


def output_file(value: str) -> Path:
    """An output file whose directory exists (or can be made) and is writable; absolute."""
    path = Path(value).expanduser().resolve()
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{value} is a directory, expected a file name")
    output_dir(str(path.parent))
    return path
