"""msgpack codec for the wire models.

``encode(msg)`` packs a model as a msgpack map keyed by **field tag** (a small int from
:data:`schemas.tags.TAGS`, one byte on the wire), not by field name; numeric arrays become ``bin``
values (little-endian, see :mod:`schemas.arrays`), nested models nested maps keyed by tag too, and
``None`` fields are left out. ``decode(data, Model)`` maps tags back to names (ignoring tags it
does not know: a newer writer's fields) and validates; it never raises on bad bytes: it returns
the model, or a :class:`Rejection` whose ``reason`` is one of :data:`REASONS`.
"""

from __future__ import annotations

import reprlib
import types
import typing
from dataclasses import dataclass
from functools import cache
from typing import Any, TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from .models import READABLE_VERSIONS, Envelope
from .tags import NAMES, TAGS

__all__ = [
    "MAX_MESSAGE_BYTES",
    "REASONS",
    "Rejection",
    "decode",
    "encode",
    "peek",
    "tag_map",
    "untag_map",
    "with_fields",
]

MAX_MESSAGE_BYTES = 8 * 1024 * 1024

REASONS = (
    "too_large",  # payload over MAX_MESSAGE_BYTES
    "malformed",  # not msgpack, truncated, not a map, or a map key that is not an integer tag
    "schema_version",  # missing or unsupported schema_version
    "non_finite",  # NaN or infinity in a number or array
    "not_positive_definite",  # a covariance that is not positive definite
    "invalid",  # any other schema violation (missing field, wrong shape or type, bad name)
)

M = TypeVar("M", bound=BaseModel)

_VERSION_TAG = TAGS["schema_version"]

# The repr of a value from a payload in a Rejection's detail: bounded in depth and length (the repr of
# 1,000 nested lists raised RecursionError, which took the reader down with it).
_repr = reprlib.Repr()
_repr.maxlevel, _repr.maxstring, _repr.maxother, _repr.maxlist, _repr.maxdict = 3, 40, 40, 4, 4
_payload_repr = _repr.repr


@dataclass(frozen=True)
class Rejection:
    """Why a payload was refused. ``reason`` is a short code from REASONS, ``detail`` is for logs."""

    reason: str
    detail: str

    def __bool__(self) -> bool:  # a rejection is never a usable message
        return False


# ------------------------------------------------------------------------------ field plans


@dataclass(frozen=True)
class _Field:
    name: str
    tag: int
    part: type[BaseModel] | None  # the nested model if the value is a map (or a list of maps)
    many: bool  # a list of nested models


def _nested(annotation: Any) -> tuple[type[BaseModel] | None, bool]:
    """(nested model, is a list) of a field annotation: ``GnssFix | None`` -> (GnssFix, False)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        for arg in args:
            part, many = _nested(arg)
            if part is not None:
                return part, many
    if origin in (list, tuple) and args:
        part, _ = _nested(args[0])
        if part is not None:
            return part, True
    return None, False


@cache
def _plan(model: type[BaseModel]) -> tuple[dict[str, _Field], dict[int, _Field]]:
    """The fields of ``model`` by name and by tag (KeyError if a field has no tag)."""
    by_name: dict[str, _Field] = {}
    for name, info in model.model_fields.items():
        if name not in TAGS:
            raise KeyError(f"{model.__name__}.{name} has no wire tag: add it at the end of schemas/tags.py")
        part, many = _nested(info.annotation)
        by_name[name] = _Field(name, TAGS[name], part, many)
    return by_name, {f.tag: f for f in by_name.values()}


def _plan_every_model() -> None:
    """Every model in schemas.models has a tag for every field, or importing the codec fails."""
    from . import models

    for obj in vars(models).values():
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == models.__name__:
            _plan(obj)


_plan_every_model()


def tag_map(model: type[BaseModel], fields: dict[str, Any]) -> dict[int, Any]:
    """A name-keyed map of ``model`` (as ``model_dump`` gives it) keyed by tag, nested parts too.

    KeyError for a name that is not a field of ``model``.
    """
    by_name = _plan(model)[0]
    out: dict[int, Any] = {}
    for name, value in fields.items():
        f = by_name[name]
        if f.part is not None:
            if f.many and isinstance(value, list):
                value = [tag_map(f.part, v) if isinstance(v, dict) else v for v in value]
            elif not f.many and isinstance(value, dict):
                value = tag_map(f.part, value)
        out[f.tag] = value
    return out


class _BadKey(ValueError):
    """A map key that is not an integer tag (the payload is malformed, not merely invalid)."""


def _key_problem(key: Any, where: str) -> str:
    if isinstance(key, str) and key in TAGS:
        return (
            f"{where}map keyed by field name ({key!r}): schema_version {READABLE_VERSIONS[0]} and later key "
            f"fields by integer tag (a schema_version {READABLE_VERSIONS[0] - 1} or older writer?)"
        )
    return f"{where}map key {_payload_repr(key)} ({type(key).__name__}) is not an integer field tag"


def untag_map(model: type[BaseModel], obj: dict[Any, Any], where: str = "") -> dict[str, Any]:
    """Inverse of :func:`tag_map`; unknown tags are dropped, a non-int key raises a ValueError."""
    by_tag = _plan(model)[1]
    out: dict[str, Any] = {}
    for key, value in obj.items():
        if type(key) is not int:  # neither str nor bool (True == 1)
            raise _BadKey(_key_problem(key, where))
        f = by_tag.get(key)
        if f is None:  # a field this reader does not know (a newer writer's): ignored
            continue
        if f.part is not None:
            if f.many and isinstance(value, list):
                value = [untag_map(f.part, v, f"{where}{f.name}[{i}]: ") if isinstance(v, dict) else v
                         for i, v in enumerate(value)]  # fmt: skip
            elif not f.many and isinstance(value, dict):
                value = untag_map(f.part, value, f"{where}{f.name}: ")
        out[f.name] = value
    return out


# ------------------------------------------------------------------------------ encode/decode


def encode(msg: Envelope) -> bytes:
    """Serialise a wire model to msgpack bytes (a map keyed by field tag)."""
    fields = msg.model_dump(mode="python", exclude_none=True)
    return msgpack.packb(tag_map(type(msg), fields), use_bin_type=True)


def with_fields(data: bytes, model: type[BaseModel], **fields: Any) -> bytes:
    """``data`` (an encoded ``model``, e.g. from :func:`encode`) with ``fields`` set (None values left out):
    the top level is unpacked and packed again, its parts and arrays stay as they are."""
    obj = msgpack.unpackb(data, raw=False, strict_map_key=False)
    obj.update(tag_map(model, {k: v for k, v in fields.items() if v is not None}))
    return msgpack.packb(obj, use_bin_type=True)


def _reason(err: ValidationError) -> str:
    for e in err.errors():
        if e["type"] in ("array_finite", "finite_number"):
            return "non_finite"
        if "positive definite" in str(e.get("msg", "")):
            return "not_positive_definite"
    return "invalid"


def _unpack(data: Any, max_items: int | None = None) -> dict | Rejection:
    if not isinstance(data, bytes | bytearray | memoryview):
        return Rejection("malformed", f"payload is {type(data).__name__}, not bytes")
    if len(data) > MAX_MESSAGE_BYTES:
        return Rejection("too_large", f"{len(data)} bytes > {MAX_MESSAGE_BYTES}")
    limits = {} if max_items is None else {"max_array_len": max_items, "max_map_len": max_items}
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=False, use_list=True, **limits)
    except Exception as exc:  # msgpack raises many types (ValueError, ExtraData, FormatError, ...)
        return Rejection("malformed", f"{type(exc).__name__}: {exc}"[:200])
    if not isinstance(obj, dict):
        return Rejection("malformed", f"top level is {type(obj).__name__}, not a map")
    return obj


def decode(data: bytes, model: type[M], *, max_items: int | None = None) -> M | Rejection:
    """Decode and validate ``data`` as ``model``; a Rejection (never an exception) if it is bad.

    ``max_items`` bounds every map and array of the message (``malformed`` beyond it): for a model of
    few fields such as a SecuredMessage, whose payload stays bytes, a hostile nested structure in a
    field nobody reads is refused at the first long container instead of being built."""
    obj = _unpack(data, max_items)
    if isinstance(obj, Rejection):
        return obj
    bad = next((k for k in obj if type(k) is not int), None)
    if bad is not None:
        return Rejection("malformed", _key_problem(bad, "")[:200])
    version = obj.get(_VERSION_TAG)
    if type(version) is not int or version not in READABLE_VERSIONS:  # an int: neither True nor 1.0
        known = ", ".join(map(str, READABLE_VERSIONS))
        detail = f"schema_version {_payload_repr(version)}, this reader knows {known}"
        return Rejection("schema_version", detail)
    try:
        fields = untag_map(model, obj)
    except _BadKey as exc:
        return Rejection("malformed", str(exc)[:200])
    try:
        return model.model_validate(fields)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        return Rejection(_reason(err), f"{where}: {first['msg']}"[:200])
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:
        return Rejection("invalid", f"{type(exc).__name__}: {exc}"[:200])


def peek(data: bytes) -> dict[str, Any]:
    """The top-level fields of a payload by name, unvalidated (nested parts stay keyed by tag).

    For cheap routing and bookkeeping (``peek(p).get("seq")``) where the payload is decoded
    properly elsewhere; ``{}`` if it is not a tagged msgpack map. Unknown tags are dropped.
    """
    obj = _unpack(data)
    if isinstance(obj, Rejection):
        return {}
    return {NAMES[k]: v for k, v in obj.items() if type(k) is int and k in NAMES}
