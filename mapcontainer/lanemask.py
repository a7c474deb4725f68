"""The lane-marking mask on the wire: a 1-bit grayscale PNG (``lane_mask_png`` of the sensor messages).

Why not only OpenCV: ``cv2.imencode`` and ``cv2.imdecode`` move a bilevel PNG's pixels through libpng's
per-pixel bit packing, which costs more than the compression itself: 2.3 ms to encode and 1.7 ms to
decode a 1280 x 720 mask here, for every camera frame of every vehicle. numpy packs and unpacks the
bits and zlib deflates them in about a quarter of that. :func:`encode` writes what OpenCV writes
with ``IMWRITE_PNG_BILEVEL``, ``IMWRITE_PNG_COMPRESSION`` 1 and ``IMWRITE_PNG_STRATEGY_RLE``: the
same chunks, no row filter, the same zlib settings and header, byte for byte; any PNG decoder reads
it. :func:`decode` reads that layout itself and hands every other PNG (other bit depths, colour, row
filters, interlacing) to ``cv2.imdecode``.

Resolution: the map matcher computes its lane distance transform at most ``lane_dt_max_width_px``
wide (``MatcherParams``) and pools a wider mask by an integer factor first (:func:`pool`). A vehicle
that sends its mask to the host (centralized mode) pools it with the same function before encoding
(:func:`pool_png`), so the bytes on the air are the pixels the host uses: the host's poses are the
same, and the mask is about a third of the size. The PNG's own header says the resolution
(:func:`png_size`); a reader scales pixel coordinates by mask width / camera width.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

__all__ = ["decode", "encode", "pool", "pool_factor", "pool_png", "png_size"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IDAT_SIZE = 8192  # libpng's: the compressed data in chunks of at most this many bytes
_MAX_PIXELS = 1 << 30  # OpenCV's own limit (CV_IO_MAX_IMAGE_PIXELS)
_IEND = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def encode(mask: np.ndarray) -> bytes:
    """A 2-D uint8 mask (nonzero = marking) as a 1-bit grayscale PNG."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.uint8 or mask.size == 0:
        raise ValueError(f"the lane mask must be a non-empty 2-D uint8 array, got {mask.dtype} {mask.shape}")
    h, w = mask.shape
    rows = np.zeros((h, 1 + (w + 7) // 8), dtype=np.uint8)  # each row: filter type 0 (none), then the bits
    rows[:, 1:] = np.packbits(mask != 0, axis=1)
    z = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    raw = rows.tobytes()
    idat = z.compress(raw) + z.flush()
    if len(raw) <= 16384:  # as libpng does: the header names the smallest window that covers the data
        cinfo, half = 7, 1 << 14
        while cinfo > 0 and len(raw) <= half:
            cinfo, half = cinfo - 1, half >> 1
        cmf, flg = 0x08 | cinfo << 4, idat[1] & 0xE0
        idat = bytes([cmf, flg + 0x1F - ((cmf << 8) + flg) % 0x1F]) + idat[2:]
    ihdr = struct.pack(">IIBBBBB", w, h, 1, 0, 0, 0, 0)  # bit depth 1, grayscale, deflate, no filter, no interlace
    chunks = [_chunk(b"IDAT", idat[i : i + _IDAT_SIZE]) for i in range(0, len(idat), _IDAT_SIZE)]
    return _SIGNATURE + _chunk(b"IHDR", ihdr) + b"".join(chunks) + _IEND


def decode(png: bytes, max_pixels: int = _MAX_PIXELS) -> np.ndarray:
    """A PNG as a 2-D uint8 grayscale mask (0 / 255 for a 1-bit PNG). Raises ValueError if it is not one,
    or if its header says it has more than ``max_pixels`` pixels (checked before anything is inflated)."""
    if png[12:16] == b"IHDR" and len(png) >= 24:
        w, h = struct.unpack_from(">II", png, 16)
        if w * h > max_pixels:
            raise ValueError(f"lane mask of {w}x{h} pixels: more than {max_pixels}")
    mask = _decode_bilevel(png)
    if mask is None:
        try:
            mask = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
        except cv2.error:  # e.g. an empty buffer
            mask = None
        if mask is None:
            raise ValueError("lane_mask_png does not decode as an image")
    return mask


def _decode_bilevel(png: bytes) -> np.ndarray | None:
    """The mask of an unfiltered, non-interlaced 1-bit grayscale PNG; None for any other PNG or anything
    malformed (left to OpenCV, which says what is wrong)."""
    if not png.startswith(_SIGNATURE):
        return None
    i, size, header, idat = len(_SIGNATURE), len(png), None, []
    while i + 12 <= size:
        (n,) = struct.unpack_from(">I", png, i)
        kind, end = png[i + 4 : i + 8], i + 8 + n
        if end + 4 > size or struct.unpack_from(">I", png, end)[0] != zlib.crc32(png[i + 4 : end]):
            return None
        if header is None and kind != b"IHDR":
            return None
        if kind == b"IHDR":
            header = struct.unpack_from(">IIBBBBB", png, i + 8) if n == 13 else None
            if header is None or header[2:] != (1, 0, 0, 0, 0):
                return None
        elif kind == b"IDAT":
            idat.append(png[i + 8 : end])
        elif kind == b"IEND":
            break
        i = end + 4
    else:
        return None  # no IEND
    w, h = header[0], header[1]
    if not 0 < w * h <= _MAX_PIXELS:
        return None
    stride = 1 + (w + 7) // 8
    try:  # at most one byte more than the image needs: a stream that inflates beyond it is not ours
        raw = zlib.decompressobj().decompress(b"".join(idat), h * stride + 1)
    except zlib.error:
        return None
    if len(raw) != h * stride:
        return None
    rows = np.frombuffer(raw, np.uint8).reshape(h, stride)
    if rows[:, 0].any():  # a row filter: OpenCV's decoder undoes it
        return None
    return np.unpackbits(rows[:, 1:], axis=1, count=w) * np.uint8(255)


def pool_factor(width_px: int, max_width_px: int) -> int:
    """The smallest integer k with ``width_px / k <= max_width_px`` (1: the mask is used as it is)."""
    if width_px <= 0 or max_width_px <= 0:
        raise ValueError(f"widths must be positive, got width_px={width_px}, max_width_px={max_width_px}")
    return -(-int(width_px) // int(max_width_px))


def pool(mask: np.ndarray, max_width_px: int) -> np.ndarray:
    """The mask at most ``max_width_px`` wide: max-pooled by k = :func:`pool_factor` (a k x k block with
    any marking pixel is marking, 255; else 0). Rows and columns past the last whole block are dropped,
    so the result is (H // k, W // k). A mask already narrow enough comes back unchanged (k = 1).

    The map matcher pools with this function before its distance transform, and a vehicle before it
    sends the mask (:func:`pool_png`): pooling a pooled mask again is the identity, so the host sees
    the same pixels whichever of the two pooled it.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"the lane mask must be 2-D, got shape {mask.shape}")
    k = pool_factor(mask.shape[1], max_width_px)
    if k == 1:
        return mask
    h, w = mask.shape[0] // k * k, mask.shape[1] // k * k
    if h == 0:
        raise ValueError(f"lane mask {mask.shape} has fewer rows than the pooling factor {k}")
    small = cv2.resize(
        np.ascontiguousarray(mask[:h, :w], dtype=np.uint8), (w // k, h // k), interpolation=cv2.INTER_AREA
    )
    return cv2.threshold(small, 0, 255, cv2.THRESH_BINARY)[1]  # the block's mean > 0: a marking pixel in it


def png_size(png: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's header, without inflating anything; None if it has no IHDR first."""
    if len(png) < 24 or not png.startswith(_SIGNATURE) or png[12:16] != b"IHDR":
        return None
    w, h = struct.unpack_from(">II", png, 16)
    return int(w), int(h)


def pool_png(png: bytes, max_width_px: int, max_pixels: int = _MAX_PIXELS) -> bytes:
    """A lane-mask PNG at most ``max_width_px`` wide: :func:`pool` of its mask, re-encoded; the same
    bytes if it is already narrow enough (or empty). Raises ValueError as :func:`decode` does."""
    if not png:
        return png
    size = png_size(png)
    if size is not None and pool_factor(size[0], max_width_px) == 1:
        return png
    mask = decode(png, max_pixels)
    if pool_factor(mask.shape[1], max_width_px) == 1:
        return png
    return encode(pool(mask, max_width_px))
