"""Typed numeric arrays for the wire models.

In Python an array field holds a read-only ``numpy.ndarray`` of the field's dtype and shape.
On the wire (msgpack) it is a ``bin`` holding the array's values, little-endian, row-major;
the shape follows from the field's declared shape (one free leading dimension at most).
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import GetCoreSchemaHandler, GetJsonSchemaHandler
from pydantic_core import PydanticCustomError, core_schema

__all__ = ["ArraySpec", "F16", "F32", "I16", "U8", "U32", "cov_from_upper", "cov_to_upper"]


class ArraySpec:
    """Pydantic metadata for an array field: dtype and shape (``None`` = any length)."""

    def __init__(self, dtype: str, shape: tuple[int | None, ...], finite: bool = True):
        if sum(s is None for s in shape) > 1:
            raise ValueError(f"at most one free dimension, got shape {shape}")
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.shape = shape
        self.finite = finite

    # -- validation ---------------------------------------------------------------------------
    def _validate(self, value: Any) -> np.ndarray:
        if isinstance(value, bytes | bytearray | memoryview):
            raw = bytes(value)
            if len(raw) % self.dtype.itemsize:
                raise PydanticCustomError(
                    "array_bytes",
                    "{n} bytes is not a whole number of {dtype} values",
                    {"n": len(raw), "dtype": self.dtype.name},
                )
            arr = np.frombuffer(raw, dtype=self.dtype)
            fixed = int(np.prod([s for s in self.shape if s is not None], dtype=int))
            if None in self.shape:
                if fixed == 0 or arr.size % fixed:
                    raise PydanticCustomError(
                        "array_shape",
                        "{n} values do not fill rows of shape {shape}",
                        {"n": arr.size, "shape": str(self.shape)},
                    )
                shape = tuple(arr.size // fixed if s is None else s for s in self.shape)
            else:
                shape = self.shape
            try:
                arr = arr.reshape(shape)
            except ValueError:
                raise PydanticCustomError(
                    "array_shape",
                    "{n} values do not make shape {shape}",
                    {"n": arr.size, "shape": str(self.shape)},
                ) from None
        else:
            if self.dtype.kind in "iu":
                info = np.iinfo(self.dtype)
                raw = np.asarray(value)
                if raw.dtype.kind == "f" and not np.all(np.isfinite(raw)):
                    raise PydanticCustomError("array_finite", "array holds NaN or infinite values", {})
                if raw.size and raw.dtype.kind in "fiu" and (raw.min() < info.min or raw.max() > info.max):
                    raise PydanticCustomError(
                        "array_range", "values outside the {dtype} range", {"dtype": self.dtype.name}
                    )
            try:
                with np.errstate(over="ignore", invalid="ignore"):  # overflow -> inf, rejected below
                    arr = np.asarray(value, dtype=self.dtype)
            except (TypeError, ValueError) as exc:
                raise PydanticCustomError("array_type", "not a numeric array: {err}", {"err": str(exc)}) from None
            if arr.size == 0 and None in self.shape:
                arr = arr.reshape(tuple(0 if s is None else s for s in self.shape))
            if arr.ndim != len(self.shape) or any(
                s is not None and s != n for s, n in zip(self.shape, arr.shape, strict=True)
            ):
                raise PydanticCustomError(
                    "array_shape",
                    "shape {got} does not match {want}",
                    {"got": str(arr.shape), "want": str(self.shape)},
                )
            arr = arr.copy()
        if self.finite and arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise PydanticCustomError("array_finite", "array holds NaN or infinite values", {})
        arr.setflags(write=False)
        return arr

    def _serialize(self, arr: np.ndarray) -> bytes:
        return np.ascontiguousarray(arr, dtype=self.dtype).tobytes()

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler):
        return core_schema.no_info_plain_validator_function(
            self._validate,
            serialization=core_schema.plain_serializer_function_ser_schema(
                self._serialize, return_schema=core_schema.bytes_schema()
            ),
        )

    def __get_pydantic_json_schema__(self, schema: Any, handler: GetJsonSchemaHandler) -> dict:
        shape = ["N" if s is None else s for s in self.shape]
        return {
            "type": "string",
            "format": "binary",
            "description": f"msgpack bin: {self.dtype.name} little-endian, row-major, shape {shape}",
            "x-dtype": self.dtype.name,
            "x-shape": shape,
        }


def F32(*shape: int | None) -> Any:
    return Annotated[np.ndarray, ArraySpec("float32", shape)]


def F16(*shape: int | None) -> Any:
    return Annotated[np.ndarray, ArraySpec("float16", shape)]


def I16(*shape: int | None) -> Any:
    return Annotated[np.ndarray, ArraySpec("int16", shape)]


def U8(*shape: int | None) -> Any:
    return Annotated[np.ndarray, ArraySpec("uint8", shape)]


def U32(*shape: int | None) -> Any:
    return Annotated[np.ndarray, ArraySpec("uint32", shape)]


def cov_to_upper(cov: np.ndarray) -> np.ndarray:
    """Row-major upper triangle (diagonal included) of square matrices (..., n, n)."""
    cov = np.asarray(cov)
    n = cov.shape[-1]
    iu = np.triu_indices(n)
    return cov[..., iu[0], iu[1]]


def cov_from_upper(upper: np.ndarray) -> np.ndarray:
    """Inverse of :func:`cov_to_upper`: symmetric matrices from their upper triangles (..., k)."""
    upper = np.asarray(upper, dtype=float)
    k = upper.shape[-1]
    n = int(round((np.sqrt(8 * k + 1) - 1) / 2))
    if n * (n + 1) // 2 != k:
        raise ValueError(f"{k} values are not the upper triangle of a square matrix")
    iu = np.triu_indices(n)
    out = np.zeros(upper.shape[:-1] + (n, n))
    out[..., iu[0], iu[1]] = upper
    out[..., iu[1], iu[0]] = upper
    return out
