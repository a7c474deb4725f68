"""msgpack codec for the wire models.

``encode(msg)`` packs a model as a msgpack map keyed by field name; numeric arrays become
``bin`` values (little-endian, see :mod:`schemas.arrays`), nested models nested maps, and
``None`` fields are left out. ``decode(data, Model)`` never raises on bad bytes: it returns the
model, or a :class:`Rejection` whose ``reason`` is one of :data:`REASONS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from .models import SCHEMA_VERSION, Envelope

__all__ = ["MAX_MESSAGE_BYTES", "REASONS", "Rejection", "decode", "encode"]

MAX_MESSAGE_BYTES = 8 * 1024 * 1024

REASONS = (
    "too_large",  # payload over MAX_MESSAGE_BYTES
    "malformed",  # not msgpack, truncated, or not a map
    "schema_version",  # missing or unsupported schema_version
    "non_finite",  # NaN or infinity in a number or array
    "not_positive_definite",  # a covariance that is not positive definite
    "invalid",  # any other schema violation (missing field, wrong shape or type, bad name)
)

M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True)
class Rejection:
    """Why a payload was refused. ``reason`` is a short code from REASONS, ``detail`` is for logs."""

    reason: str
    detail: str

    def __bool__(self) -> bool:  # a rejection is never a usable message
        return False


def encode(msg: Envelope) -> bytes:
    """Serialise a wire model to msgpack bytes."""
    return msgpack.packb(msg.model_dump(mode="python", exclude_none=True), use_bin_type=True)


def _reason(err: ValidationError) -> str:
    for e in err.errors():
        if e["type"] in ("array_finite", "finite_number"):
            return "non_finite"
        if "positive definite" in str(e.get("msg", "")):
            return "not_positive_definite"
    return "invalid"


def decode(data: bytes, model: type[M]) -> M | Rejection:
    """Decode and validate ``data`` as ``model``; a Rejection (never an exception) if it is bad."""
    if not isinstance(data, bytes | bytearray | memoryview):
        return Rejection("malformed", f"payload is {type(data).__name__}, not bytes")
    if len(data) > MAX_MESSAGE_BYTES:
        return Rejection("too_large", f"{len(data)} bytes > {MAX_MESSAGE_BYTES}")
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises many types (ValueError, ExtraData, FormatError, ...)
        return Rejection("malformed", f"{type(exc).__name__}: {exc}"[:200])
    if not isinstance(obj, dict):
        return Rejection("malformed", f"top level is {type(obj).__name__}, not a map")
    version = obj.get("schema_version")
    if type(version) is not int or version != SCHEMA_VERSION:  # an int: neither True nor 1.0
        return Rejection("schema_version", f"schema_version {version!r}, this reader knows {SCHEMA_VERSION}")
    try:
        return model.model_validate(obj)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        return Rejection(_reason(err), f"{where}: {first['msg']}"[:200])
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:
        return Rejection("invalid", f"{type(exc).__name__}: {exc}"[:200])
