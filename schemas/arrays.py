"""Typed numeric arrays for the wire models.

In Python an array field holds a read-only ``numpy.ndarray`` of the field's dtype and shape.
On the wire (msgpack) it is a ``bin`` holding the array's values, little-endian, row-major;
the shape follows from the field's declared shape (one free leading dimension at most).
"""

from __future__ import annotations

from functools import cache
from typing import Annotated, Any

import numpy as np
from pydantic import GetCoreSchemaHandler, GetJsonSchemaHandler
from pydantic_core import PydanticCustomError, core_schema

__all__ = ["ArraySpec", "Cov", "CovSpec", "F16", "F32", "I16", "U8", "U32", "cov_from_upper", "cov_to_upper"]


class ArraySpec:
    """Pydantic metadata for an array field: dtype and shape (``None`` = any length)."""

    def __init__(self, dtype: str, shape: tuple[int | None, ...], finite: bool = True):
        if sum(s is None for s in shape) > 1:
            raise ValueError(f"at most one free dimension, got shape {shape}")
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.shape = shape
        self.finite = finite
        self._fixed = int(np.prod([s for s in shape if s is not None], dtype=int))  # values per row

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
            fixed = self._fixed
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
        if self.finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
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


class CovSpec(ArraySpec):
    """Covariance matrices of size n: in Python float32 upper triangles, shape (k,) or (N, k) with
    k = n (n + 1) / 2, each positive definite (checked on validation, one batched Cholesky); on the
    wire each matrix is n standard deviations (float16, m or rad) then the n (n - 1) / 2 correlation
    coefficients of its strict upper triangle, row-major, as int8 (steps of 1/127) or int16 (steps
    of 1/32767); the type's most negative value is invalid. The ETSI
    Collective Perception Message's habit: 2n + n(n-1)/2 (int8) or 2n + n(n-1) (int16) bytes per
    matrix instead of 4k. Strongly correlated matrices (a pose: yaw with lateral position, pitch
    with height) want int16; int8 distorts their small eigenvalues.

    The encoder keeps the matrix positive definite: if rounding the correlations breaks that, they
    are shrunk towards zero (a factor 0.98 at a time) until it holds. Standard deviations beyond
    float16's range (65504) are clipped there.
    """

    _SHRINK = 0.98

    def __init__(self, n: int, many: bool, corr: str = "int8"):
        self.n = n
        self.k = n * (n + 1) // 2
        super().__init__("float32", (None, self.k) if many else (self.k,))
        self.corr = np.dtype(corr).newbyteorder("<")
        if self.corr.kind != "i":
            raise ValueError(f"correlations are signed integers, got {corr}")
        self.q = float(np.iinfo(self.corr).max)
        self.row_bytes = 2 * n + self.corr.itemsize * n * (n - 1) // 2
        self._iu = _triu(n, 1)
        self._row = np.dtype([("sigma", "<f2", (n,)), ("rho", self.corr, (n * (n - 1) // 2,))])  # one matrix
        # Upper triangle (diagonal included) element -> column of [1, rho_01, rho_02, ...]: 0 on the diagonal
        strict = {ij: 1 + c for c, ij in enumerate(zip(*self._iu, strict=True))}
        self._rho_col = np.array([strict.get(ij, 0) for ij in zip(*_triu(n), strict=True)])

    def _validate(self, value: Any) -> np.ndarray:
        if not isinstance(value, bytes | bytearray | memoryview):
            arr = super()._validate(value)
            _require_pd(arr)
            return arr
        raw = bytes(value)
        if len(raw) % self.row_bytes or (self.shape[0] is not None and len(raw) != self.row_bytes):
            raise PydanticCustomError(
                "array_bytes",
                "{n} bytes are not whole covariances of {rb} bytes each",
                {"n": len(raw), "rb": self.row_bytes},
            )
        rows = np.frombuffer(raw, dtype=self._row)
        sigma = rows["sigma"].astype(np.float64)
        rho_q = rows["rho"].astype(np.float64)
        if not np.isfinite(sigma).all():
            raise PydanticCustomError("array_finite", "array holds NaN or infinite values", {})
        if (sigma <= 0).any():
            raise PydanticCustomError("covariance", "not positive definite: a standard deviation <= 0", {})
        if (rho_q < -self.q).any():
            raise PydanticCustomError("array_range", "correlation code {c} is not used", {"c": -self.q - 1})
        # Straight to the upper triangle: C_ij = sigma_i rho_ij sigma_j (rho_ii = 1), no full matrices.
        # Finite by construction: |sigma| <= 65504 (float16), |rho| <= 1, so |C_ij| < 4.3e9 fits float32.
        rho = np.empty((len(rows), 1 + rho_q.shape[1]))
        rho[:, 0] = 1.0
        rho[:, 1:] = rho_q / self.q
        i, j = _triu(self.n)
        cov = (sigma[:, i] * rho[:, self._rho_col] * sigma[:, j]).astype(self.dtype)
        if self.shape[0] is not None:
            cov = cov[0]
        _require_pd(cov)
        cov.setflags(write=False)
        return cov

    def _serialize(self, arr: np.ndarray) -> bytes:
        C = cov_from_upper(np.asarray(arr, dtype=np.float64).reshape(-1, self.k))
        sigma = np.sqrt(np.maximum(np.diagonal(C, axis1=1, axis2=2), 0.0))
        sigma_q = np.clip(sigma, 0.0, float(np.finfo(np.float16).max)).astype("<f2")
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = C / (sigma[:, :, None] * sigma[:, None, :])
        rho = np.nan_to_num(rho[:, self._iu[0], self._iu[1]])
        q = self._quantize(rho)
        bad = ~self._pd(sigma_q.astype(np.float64), q) & np.all(sigma_q > 0, axis=1)
        for _ in range(200):  # rare: shrink the correlations of the matrices that rounding broke
            if not bad.any():
                break
            rho[bad] *= self._SHRINK
            q[bad] = self._quantize(rho[bad])
            bad[bad] = ~self._pd(sigma_q[bad].astype(np.float64), q[bad])
        return np.concatenate([sigma_q.view(np.uint8), q.view(np.uint8)], axis=1).tobytes()

    def _quantize(self, rho: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(rho * self.q), -self.q, self.q).astype(self.corr)

    def _pd(self, sigma: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Per matrix: positive definite after decoding (sigmas > 0, correlation matrix Cholesky-able)."""
        rho = np.zeros((len(q), self.n, self.n))
        rho[:, np.arange(self.n), np.arange(self.n)] = 1.0
        rho[:, self._iu[0], self._iu[1]] = rho[:, self._iu[1], self._iu[0]] = q / self.q
        ok = np.all(sigma > 0, axis=1)
        try:
            np.linalg.cholesky(rho)
            return ok
        except np.linalg.LinAlgError:  # find which
            return ok & (np.linalg.eigvalsh(rho)[:, 0] > 1e-12)

    def __get_pydantic_json_schema__(self, schema: Any, handler: GetJsonSchemaHandler) -> dict:
        many = "N matrices, each " if self.shape[0] is None else ""
        return {
            "type": "string",
            "format": "binary",
            "description": f"msgpack bin: {many}{self.n}x{self.n} covariance as {self.n} float16 standard "
            f"deviations then {self.n * (self.n - 1) // 2} {self.corr.name} correlations (1/{self.q:.0f} "
            f"steps) of the strict upper triangle, row-major, little-endian; {self.row_bytes} bytes per matrix",
            "x-covariance": self.n,
            "x-correlation-dtype": self.corr.name,
            "x-bytes-per-matrix": self.row_bytes,
        }


def Cov(n: int, many: bool = False, corr: str = "int8") -> Any:
    """A covariance field (see :class:`CovSpec`): one n x n matrix, or N of them with ``many``."""
    return Annotated[np.ndarray, CovSpec(n, many, corr)]


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


@cache
def _triu(n: int, k: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, k)``, computed once (it is slow next to the small arrays it indexes)."""
    iu = np.triu_indices(n, k)
    for a in iu:
        a.setflags(write=False)
    return iu


@cache
def _tri_size(k: int) -> int:
    """n such that k = n (n + 1) / 2; ValueError if there is none."""
    n = int(round((np.sqrt(8 * k + 1) - 1) / 2))
    if n * (n + 1) // 2 != k:
        raise ValueError(f"{k} values are not the upper triangle of a square matrix")
    return n


def _require_pd(upper: np.ndarray) -> None:
    """A "not positive definite" validation error unless every matrix (upper triangles (..., k)) is.

    One batched Cholesky factorisation over all matrices, in float64 of the stored values.
    """
    if upper.size == 0:
        return
    try:
        np.linalg.cholesky(cov_from_upper(upper))
    except np.linalg.LinAlgError:
        raise PydanticCustomError("covariance", "not positive definite", {}) from None


def cov_to_upper(cov: np.ndarray) -> np.ndarray:
    """Row-major upper triangle (diagonal included) of square matrices (..., n, n)."""
    cov = np.asarray(cov)
    iu = _triu(cov.shape[-1])
    return cov[..., iu[0], iu[1]]


def cov_from_upper(upper: np.ndarray) -> np.ndarray:
    """Inverse of :func:`cov_to_upper`: symmetric matrices from their upper triangles (..., k)."""
    upper = np.asarray(upper, dtype=float)
    n = _tri_size(upper.shape[-1])
    iu = _triu(n)
    out = np.empty(upper.shape[:-1] + (n, n))
    out[..., iu[0], iu[1]] = upper
    out[..., iu[1], iu[0]] = upper
    return out
