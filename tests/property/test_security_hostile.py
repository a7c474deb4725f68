"""Hostile bytes never make the Verifier raise: random bytes, maps of the envelope's tags with values of
any type, and signed messages with bytes flipped, cut, inserted or removed. What it refuses it counts
under one of its reasons; a changed message passes only if it still means the same."""

from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapcontainer.security import REASONS, Signer, Verified, Verifier, issue, make_ca
from schemas import LocalizationQuality, Rejection, SecuredMessage, VehiclePrior, decode, encode

NOW = 1.8e9
FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

CA = make_ca("fleet-ca", now=NOW - 3600)
CV0 = issue(CA, "cv0", 86400.0, NOW - 600)
PAYLOAD = encode(
    VehiclePrior(
        fleet="f",
        sender="cv0",
        seq=1,
        t_meas=1.0,
        t_sent=1.0,
        pose=[1.0, 2.0, 0.0, 0.0, 0.0, 0.5],
        pose_cov=np.eye(6)[np.triu_indices(6)] * 0.1,
        v_map=[1.0, 0.0, 0.0],
        quality=LocalizationQuality(mode="map_matching"),
    )
)
_signer = Signer(CV0, math.inf)
FIRST = _signer.sign(PAYLOAD, NOW - 0.5)  # with the certificate
SIGNED = {"full": Signer(CV0).sign(PAYLOAD, NOW), "digest": _signer.sign(PAYLOAD, NOW)}
ENVELOPE_TAGS = [0, 83, 84, 85, 86, 87, 88, 89, 90, 91, 92]


def fresh() -> Verifier:
    """A verifier that knows cv0's certificate (from a message of its own)."""
    v = Verifier(CA.certificate, 2.0)
    assert v.verify(FIRST, NOW - 0.5)
    return v


# One verifier for every example (a fresh one costs two signature checks): it learns nothing a hostile
# example could change but the replay table, and the original message's meaning passes at most once.
VERIFIER = fresh()


def check(v: Verifier, data: bytes, expected: str | None = "cv0") -> Verified | Rejection:
    before = sum(v.rejected.values())
    out = v.verify(data, NOW, expected)
    assert isinstance(out, Verified | Rejection)
    if isinstance(out, Rejection):
        assert out.reason in REASONS and len(out.detail) <= 200
        assert sum(v.rejected.values()) == before + 1 and v.rejected[out.reason] >= 1
    return out


def same_meaning(data: bytes, original: bytes) -> bool:
    a, b = decode(data, SecuredMessage), decode(original, SecuredMessage)
    return (a.payload, a.t_gen_us, a.signature) == (b.payload, b.t_gen_us, b.signature)


@FAST
@given(st.binary(max_size=600))
def test_random_bytes_never_raise(data: bytes) -> None:
    assert isinstance(check(VERIFIER, data), Rejection)


scalars = (
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=20)
    | st.binary(max_size=80)
)  # fmt: skip
values = scalars | st.lists(scalars, max_size=3) | st.dictionaries(st.sampled_from(ENVELOPE_TAGS), scalars, max_size=6)


@settings(FAST, max_examples=100)  # drawing the maps is most of the time
@given(
    st.sampled_from(sorted(SIGNED)),
    st.dictionaries(st.sampled_from(ENVELOPE_TAGS) | st.integers(-5, 200), values, max_size=4),
    st.dictionaries(st.sampled_from(ENVELOPE_TAGS[1:7]), values, max_size=3),
)
def test_signed_maps_with_fields_of_any_value_never_raise(kind: str, fields: dict, cert_fields: dict) -> None:
    raw = msgpack.unpackb(SIGNED[kind], strict_map_key=False)
    raw.update(fields)
    if isinstance(raw.get(90), dict):
        raw[90].update(cert_fields)
    data = msgpack.packb(raw, use_bin_type=True)
    out = check(VERIFIER, data)
    if isinstance(out, Verified):
        assert same_meaning(data, SIGNED[kind]) and out.payload == PAYLOAD


@FAST
@given(
    st.sampled_from(sorted(SIGNED)),
    st.lists(
        st.tuples(st.sampled_from(["flip", "cut", "insert", "delete"]), st.integers(0, 10**6), st.integers(1, 255)),
        min_size=1,
        max_size=4,
    ),
)
def test_mutated_signed_messages_never_raise_nor_pass_changed(kind: str, edits: list) -> None:
    original = SIGNED[kind]
    data = bytearray(original)
    for op, at, byte in edits:
        at %= len(data) + 1
        if op == "flip" and at < len(data):
            data[at] ^= byte
        elif op == "cut":
            del data[at:]
        elif op == "insert":
            data.insert(at, byte)
        elif op == "delete" and at < len(data):
            del data[at]
        if not data:
            data = bytearray(b"\x00")
    out = check(VERIFIER, bytes(data))
    if isinstance(out, Verified):
        assert same_meaning(bytes(data), original) and out.payload == PAYLOAD


@FAST
@given(st.sampled_from(sorted(SIGNED)), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=70))
def test_any_time_and_expected_sender_never_raise(kind: str, now: float, expected: str) -> None:
    out = VERIFIER.verify(SIGNED[kind], now, expected)
    assert isinstance(out, Verified | Rejection)
    if isinstance(out, Verified):
        assert expected == "cv0" and abs(now - NOW) <= 2.0
