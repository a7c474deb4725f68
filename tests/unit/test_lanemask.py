"""The lane mask's 1-bit PNG: what any PNG decoder reads, what OpenCV writes, and bad input."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from mapcontainer import lanemask
from mapcontainer.sim import World, load_scenario

OPENCV_BILEVEL = [
    cv2.IMWRITE_PNG_BILEVEL,
    1,
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]


def _masks() -> list[np.ndarray]:
    """Simulated lane masks (1280 x 720) and small ones of awkward widths."""
    world = World(load_scenario("paper-urban"), seed=0)
    states = world.states(0.0)
    out = [world.sense(0, 0.0, vid, states)[1].camera.lane_mask for vid in ("cv0", "cv1")]
    rng = np.random.default_rng(3)
    for h, w in [(1, 1), (5, 7), (9, 8), (33, 129), (100, 300), (128, 1000), (131, 1000)]:
        out.append(np.where(rng.random((h, w)) < 0.3, 255, 0).astype(np.uint8))
    out.append(np.zeros((4, 12), np.uint8))
    return out


@pytest.fixture(scope="module")
def masks() -> list[np.ndarray]:
    return _masks()


def test_any_png_decoder_reads_it_and_it_reads_opencvs(masks):
    for m in masks:
        png = lanemask.encode(m)
        assert np.array_equal(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE), m)
        assert np.array_equal(lanemask.decode(png), m)
        ok, theirs = cv2.imencode(".png", m, OPENCV_BILEVEL)
        assert ok and np.array_equal(lanemask.decode(theirs.tobytes()), m)


def test_it_writes_what_opencv_writes(masks):
    """Byte for byte (the same chunks, zlib settings and header): the wire bytes, and so the byte counts of
    the experiments, do not depend on which of the two encoded a mask."""
    for m in masks:
        ok, theirs = cv2.imencode(".png", m, OPENCV_BILEVEL)
        assert ok and lanemask.encode(m) == theirs.tobytes()


def test_other_pngs_are_decoded_by_opencv(masks):
    m = masks[0]
    for params in ([], [cv2.IMWRITE_PNG_COMPRESSION, 9], [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 9]):
        ok, png = cv2.imencode(".png", m, params)  # 8-bit, or 1-bit with row filters
        assert ok and np.array_equal(lanemask.decode(png.tobytes()), m)
    ok, rgb = cv2.imencode(".png", cv2.cvtColor(m, cv2.COLOR_GRAY2BGR))
    assert ok and np.array_equal(lanemask.decode(rgb.tobytes()), m)


def _corrupt(png: bytes, at: int) -> bytes:
    return png[:at] + bytes([png[at] ^ 0x55]) + png[at + 1 :]


@pytest.mark.parametrize(
    "bad",
    [
        b"",
        b"not a png at all",
        b"\x89PNG\r\n\x1a\n",
        "truncated",
        "idat crc",
        "ihdr says 2-bit",
    ],
)
def test_bad_input_is_a_value_error(bad, masks):
    png = lanemask.encode(masks[3])
    if bad == "truncated":
        bad = png[: len(png) // 2]
    elif bad == "idat crc":
        bad = _corrupt(png, png.index(b"IDAT") + 6)
    elif bad == "ihdr says 2-bit":  # a consistent chunk that lies about the data
        ihdr = struct.pack(">IIBBBBB", 7, 5, 2, 0, 0, 0, 0)
        body = b"IHDR" + ihdr
        bad = png[:8] + struct.pack(">I", 13) + body + struct.pack(">I", zlib.crc32(body)) + png[33:]
    with pytest.raises(ValueError, match="does not decode"):
        lanemask.decode(bad)


def test_encode_takes_a_2d_uint8_mask_only():
    for bad in (np.zeros((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8), np.zeros((0, 5), np.uint8)):
        with pytest.raises(ValueError, match="2-D uint8"):
            lanemask.encode(bad)


def test_a_mask_larger_than_the_camera_is_refused_before_it_is_inflated():
    """A blank 1-bit PNG compresses about 9000 to 1: a few kB on the wire would inflate to gigabytes at
    the decoder's own limit. The vehicle passes the camera's size, and the header is checked first."""
    big = lanemask.encode(np.zeros((4000, 8000), np.uint8))
    assert len(big) < 20_000
    with pytest.raises(ValueError, match="4000 pixels: more than 307200"):
        lanemask.decode(big, max_pixels=640 * 480)
    small = lanemask.encode(np.full((480, 640), 255, np.uint8))
    assert lanemask.decode(small, max_pixels=640 * 480).shape == (480, 640)
