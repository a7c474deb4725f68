"""Signed V2X messages: signing and verifying, every rejection reason, the bounded caches, credentials on
disk, the README's recipe, ``mapc keys init`` and ``mapc bench security``."""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import msgpack
import numpy as np
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519

from mapcontainer.cli import main
from mapcontainer.config import ConfigError
from mapcontainer.security import (
    CA_NAME,
    REASONS,
    Credentials,
    Signer,
    Verified,
    Verifier,
    certificate_bytes,
    certificate_digest,
    issue,
    load_certificate,
    load_credentials,
    make_ca,
    save_credentials,
)
from mapcontainer.security_bench import bench_security
from schemas import (
    Certificate,
    LocalizationQuality,
    Rejection,
    SecuredMessage,
    VehiclePrior,
    decode,
    encode,
)

NOW = 1.8e9  # Unix time of these tests (2027)
WINDOW_S = 2.0
README = Path(__file__).resolve().parents[2] / "schemas" / "README.md"


def prior(sender: str, seq: int = 1) -> bytes:
    msg = VehiclePrior(
        fleet="f",
        sender=sender,
        seq=seq,
        t_meas=12.3,
        t_sent=12.35,
        pose=[10.0, -4.0, 0.2, 0.0, 0.01, 1.1],
        pose_cov=np.diag([0.04, 0.04, 0.01, 1e-4, 1e-4, 4e-4])[np.triu_indices(6)],
        v_map=[5.0, 1.0, 0.0],
        quality=LocalizationQuality(mode="map_matching"),
    )
    return encode(msg)


@pytest.fixture(scope="module")
def ca() -> Credentials:
    return make_ca("fleet-ca", now=NOW - 3600)


@pytest.fixture(scope="module")
def creds(ca: Credentials) -> dict[str, Credentials]:
    return {vid: issue(ca, vid, 86400.0, NOW - 600) for vid in ("cv0", "cv1", "cv2", "cv9")}


def verifier(ca: Credentials, **kw) -> Verifier:
    return Verifier(ca.certificate, WINDOW_S, **kw)


def assert_rejected(out: Verified | Rejection, reason: str) -> None:
    assert isinstance(out, Rejection), f"expected {reason}, accepted {out}"
    assert out.reason == reason, out
    assert out.reason in REASONS and not out and len(out.detail) <= 200


# ------------------------------------------------------------------------------ round trip


def test_sign_verify_round_trip(ca, creds) -> None:
    signer, v = Signer(creds["cv0"]), verifier(ca)
    for k in range(25):
        t = NOW + 0.1 * k
        payload = prior("cv0", seq=k)
        out = v.verify(signer.sign(payload, t), t + 0.05, expected_sender="cv0")
        assert isinstance(out, Verified), out
        assert (out.payload, out.sender) == (payload, "cv0")
        assert out.t_gen == pytest.approx(t, abs=1e-6)
        assert decode(out.payload, VehiclePrior).seq == k
    assert v.accepted == 25 and not v.rejected


def test_signed_bytes_are_the_codecs_encoding(ca, creds) -> None:
    signer = Signer(creds["cv0"])
    for t in (NOW, NOW + 0.1):  # the first with the certificate, the second with the digest
        data = signer.sign(prior("cv0"), t)
        msg = decode(data, SecuredMessage)
        assert isinstance(msg, SecuredMessage), msg
        assert encode(msg) == data
    assert msg.signer_digest == creds["cv0"].digest == certificate_digest(creds["cv0"].certificate)


def test_full_certificate_about_once_per_period(creds) -> None:
    def pattern(signer: Signer, times: list[float]) -> list[bool]:
        return [decode(signer.sign(b"x", t), SecuredMessage).certificate is not None for t in times]

    ticks = [NOW + 0.1 * k for k in range(25)]
    full = pattern(Signer(creds["cv0"], 1.0), ticks)
    assert [k for k, f in enumerate(full) if f] == [0, 10, 20]
    assert pattern(Signer(creds["cv0"], math.inf), ticks[:5]) == [True, False, False, False, False]
    assert pattern(Signer(creds["cv0"], 0.0), ticks[:3]) == [True, True, True]
    assert pattern(Signer(creds["cv0"], 1.0), [NOW, NOW + 0.5, NOW - 10.0]) == [True, False, True]  # clock went back
    with pytest.raises(ValueError, match="full_cert_every_s"):
        Signer(creds["cv0"], -1.0)


def test_generation_times_strictly_increase(ca, creds) -> None:
    signer, v = Signer(creds["cv0"], 0.0), verifier(ca)
    times = [decode(signer.sign(prior("cv0"), NOW), SecuredMessage).t_gen_us for _ in range(3)]
    assert times == [round(NOW * 1e6) + k for k in range(3)]
    signer = Signer(creds["cv0"], 0.0)
    assert all(v.verify(signer.sign(prior("cv0"), NOW), NOW) for _ in range(3))  # same instant: no replay


# ------------------------------------------------------------------------------ rejections


def test_a_bare_or_broken_message_is_unsigned(ca, creds) -> None:
    v = verifier(ca)
    for data in (prior("cv0"), b"", b"\xc1garbage", msgpack.packb([1, 2]), "text", None):
        assert_rejected(v.verify(data, NOW), "unsigned")  # type: ignore[arg-type]
    msg = decode(Signer(creds["cv0"]).sign(prior("cv0"), NOW), SecuredMessage)
    raw = msgpack.unpackb(encode(msg), strict_map_key=False)
    raw[91] = creds["cv0"].digest  # both a certificate and a digest
    assert_rejected(v.verify(msgpack.packb(raw), NOW), "unsigned")
    assert v.rejected == {"unsigned": 7}


def flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1 :]


@pytest.mark.parametrize("full", [True, False])
def test_a_flipped_payload_byte_is_forged(ca, creds, full: bool) -> None:
    signer, v = Signer(creds["cv0"]), verifier(ca)
    first = signer.sign(prior("cv0"), NOW)
    data = first if full else signer.sign(prior("cv0"), NOW + 0.1)
    if not full:
        assert v.verify(first, NOW)
    payload = prior("cv0")
    start = data.index(payload)
    for at in (start + 5, start + len(payload) // 2, start + len(payload) - 1):
        assert_rejected(v.verify(flip(data, at), NOW + 0.1), "forged")
    assert v.verify(data, NOW + 0.1), "the original still passes"


def test_a_bad_message_signature_is_forged(ca, creds) -> None:
    v = verifier(ca)
    data = Signer(creds["cv0"]).sign(prior("cv0"), NOW)
    msg = decode(data, SecuredMessage)
    sig = msg.signature
    for bad in (sig[:-1] + bytes([sig[-1] ^ 0x80]), bytes(64), b"\xff" * 64, sig[32:] + sig[:32]):
        assert_rejected(v.verify(encode(msg.model_copy(update={"signature": bad})), NOW), "forged")
    later = msg.model_copy(update={"t_gen_us": msg.t_gen_us + 1})  # the time is signed too
    assert_rejected(v.verify(encode(later), NOW), "forged")
    other = Signer(creds["cv1"]).sign(prior("cv0"), NOW)  # cv1's signature under cv0's certificate
    swapped = msg.model_copy(update={"signature": decode(other, SecuredMessage).signature})
    assert_rejected(v.verify(encode(swapped), NOW), "forged")
    assert v.rejected == {"forged": 6}


def test_a_certificate_of_another_ca_is_unknown(ca) -> None:
    other = make_ca("other-ca", now=NOW - 3600)
    intruder = issue(other, "cv0", 86400.0, NOW - 600)
    v = verifier(ca)
    assert_rejected(v.verify(Signer(intruder).sign(prior("cv0"), NOW), NOW), "unknown_certificate")
    assert "not our CA" in v.verify(Signer(intruder).sign(prior("cv0"), NOW + 0.1), NOW + 0.1).detail


def test_a_certificate_claiming_our_ca_but_signed_by_another_is_forged(ca, creds) -> None:
    other = make_ca("other-ca", now=NOW - 3600)
    fake = issue(other, "cv0", 86400.0, NOW - 600)
    cert = fake.certificate.model_copy(update={"issuer": ca.digest})  # names our CA; its signature is other's
    v = verifier(ca)
    assert_rejected(v.verify(Signer(Credentials(fake.private_key, cert)).sign(prior("cv0"), NOW), NOW), "forged")
    stolen = creds["cv0"].certificate.model_copy(update={"subject": "cv1"})  # edited after the CA signed it
    signer = Signer(Credentials(creds["cv0"].private_key, stolen))
    assert_rejected(v.verify(signer.sign(prior("cv1"), NOW), NOW), "forged")


def test_a_forged_certificate_sent_again_is_refused_without_another_signature_check(ca, creds, monkeypatch) -> None:
    """A flood of one forged certificate must not make the host check the CA's signature each time."""
    import mapcontainer.security as sec

    stolen = creds["cv0"].certificate.model_copy(update={"subject": "cv1"})
    signer = Signer(Credentials(creds["cv0"].private_key, stolen), full_cert_every_s=0.0)  # the certificate every time
    v = verifier(ca)
    checks = []
    real = sec._valid
    monkeypatch.setattr(sec, "_valid", lambda *a: checks.append(1) or real(*a))
    assert_rejected(v.verify(signer.sign(prior("cv1"), NOW), NOW), "forged")
    assert len(checks) == 1
    for k in range(1, 20):
        assert_rejected(v.verify(signer.sign(prior("cv1"), NOW + 0.01 * k), NOW + 0.01 * k), "forged")
    assert len(checks) == 1 and v.rejected == {"forged": 20}
    genuine = v.verify(Signer(creds["cv0"]).sign(prior("cv0"), NOW + 0.5), NOW + 0.5)
    assert not isinstance(genuine, sec.Rejection)  # the genuine certificate is still learnt


def test_a_certificate_outside_its_validity_is_expired(ca) -> None:
    old = issue(ca, "cv0", 60.0, NOW - 1000)  # valid NOW-1000 .. NOW-940
    future = issue(ca, "cv1", 60.0, NOW + 1000)
    v = verifier(ca)
    assert_rejected(v.verify(Signer(old).sign(prior("cv0"), NOW), NOW), "expired")
    assert_rejected(v.verify(Signer(future).sign(prior("cv1"), NOW), NOW), "expired")
    assert v.verify(Signer(old).sign(prior("cv0"), NOW - 950), NOW - 950), "valid within its validity"
    assert v.rejected == {"expired": 2}


def test_a_replay_is_refused(ca, creds) -> None:
    signer, v = Signer(creds["cv0"]), verifier(ca)
    data = signer.sign(prior("cv0"), NOW)
    assert v.verify(data, NOW)
    assert_rejected(v.verify(data, NOW + 0.5), "replayed")
    later = signer.sign(prior("cv0"), NOW + 0.1)
    assert v.verify(later, NOW + 0.2)
    assert_rejected(v.verify(later, NOW + 0.3), "replayed")
    assert_rejected(v.verify(data, NOW + 10.0), "replayed")  # long after: outside the window


def test_cheap_checks_come_before_the_signature_check(ca, creds, monkeypatch) -> None:
    """A replay, a message outside the window, an unknown digest and nested junk cost no ECDSA check; the
    inner message is not decoded before the signature holds."""
    import msgpack

    import mapcontainer.security as sec

    signer, v = Signer(creds["cv0"]), verifier(ca)
    data = signer.sign(prior("cv0"), NOW)
    assert v.verify(data, NOW)
    checks, peeked = [], []
    real_valid, real_peek = sec._valid, sec.peek
    monkeypatch.setattr(sec, "_valid", lambda *a: checks.append(1) or real_valid(*a))
    monkeypatch.setattr(sec, "peek", lambda d: peeked.append(d) or real_peek(d))
    assert_rejected(v.verify(data, NOW + 0.5), "replayed")
    assert_rejected(v.verify(signer.sign(prior("cv0"), NOW + 10.0), NOW), "replayed")  # outside the window
    other = Signer(creds["cv1"], full_cert_every_s=math.inf)
    other.sign(prior("cv1"), NOW)  # its certificate went in a message this verifier never saw
    assert_rejected(v.verify(other.sign(prior("cv1"), NOW + 0.1), NOW + 0.1), "unknown_certificate")
    nested = msgpack.packb({0: 4, 200: [[[[0] * 17]]]})  # a long array in a field nobody reads: refused unbuilt
    assert_rejected(v.verify(nested, NOW), "unsigned")
    assert checks == [] and peeked == []
    tampered = Signer(creds["cv0"], full_cert_every_s=math.inf).sign(prior("cv0"), NOW + 0.2)
    tampered = tampered[:-1] + bytes([tampered[-1] ^ 1])
    assert_rejected(v.verify(tampered, NOW + 0.2), "forged")
    assert checks == [1] and peeked == []  # forged: the payload was never decoded


def test_new_certificates_can_be_refused_unchecked(ca, creds, monkeypatch) -> None:
    """Under a flood a verifier takes known certificates only: a new one costs no CA signature check."""
    import mapcontainer.security as sec

    v = verifier(ca)
    checks = []
    real = sec._valid
    monkeypatch.setattr(sec, "_valid", lambda *a: checks.append(1) or real(*a))
    first = Signer(creds["cv0"]).sign(prior("cv0"), NOW)
    assert_rejected(v.verify(first, NOW, new_certificates=False), "unknown_certificate")
    assert checks == []
    assert v.verify(first, NOW)  # learnt when allowed: CA check and message check
    again = Signer(creds["cv0"], full_cert_every_s=0.0)
    assert v.verify(again.sign(prior("cv0"), NOW + 0.1), NOW + 0.1, new_certificates=False)  # known: fine
    assert len(checks) == 3


@pytest.mark.parametrize("offset_s", [-WINDOW_S - 0.01, WINDOW_S + 0.01, -1e6, 1e6])
def test_a_generation_time_outside_the_window_is_replayed(ca, creds, offset_s: float) -> None:
    v = verifier(ca)
    assert_rejected(v.verify(Signer(creds["cv0"]).sign(prior("cv0"), NOW + offset_s), NOW), "replayed")
    if abs(offset_s) < 60:  # within the certificate's validity
        assert v.verify(Signer(creds["cv0"]).sign(prior("cv0"), NOW + offset_s), NOW + offset_s)


def test_a_payload_of_another_sender_is_a_mismatch(ca, creds) -> None:
    v = verifier(ca)
    forged_origin = Signer(creds["cv9"]).sign(prior("cv1"), NOW)  # cv9's key speaks for cv1
    assert_rejected(v.verify(forged_origin, NOW, expected_sender="cv1"), "sender_mismatch")
    assert_rejected(v.verify(Signer(creds["cv9"]).sign(prior("cv1"), NOW), NOW), "sender_mismatch")
    wrong_key = Signer(creds["cv0"]).sign(prior("cv0"), NOW)  # arrived on cv1's key
    assert_rejected(v.verify(wrong_key, NOW, expected_sender="cv1"), "sender_mismatch")
    no_sender = Signer(creds["cv2"]).sign(b"\xc1 not a message", NOW)
    assert_rejected(v.verify(no_sender, NOW), "sender_mismatch")
    assert v.rejected == {"sender_mismatch": 4}
    assert v.verify(Signer(creds["cv0"]).sign(prior("cv0"), NOW + 0.1), NOW + 0.1, "cv0")  # a mismatch is not recorded


def test_an_unknown_digest_is_refused_until_the_certificate_comes(ca, creds) -> None:
    signer, v = Signer(creds["cv0"], 1.0), verifier(ca)
    sent = [(NOW + 0.1 * k, signer.sign(prior("cv0", k), NOW + 0.1 * k)) for k in range(15)]
    out = [v.verify(data, t, "cv0") for t, data in sent[1:]]  # the first message (the certificate) was lost
    assert all(o.reason == "unknown_certificate" for o in out[:9]), out[:9]
    assert all(isinstance(o, Verified) for o in out[9:]), out[9:]  # from the second certificate on (k = 10)
    assert v.rejected == {"unknown_certificate": 9} and v.accepted == 5


# ------------------------------------------------------------------------------ bounds


def test_the_certificate_cache_is_bounded_and_keeps_the_recently_used(ca, creds) -> None:
    v = verifier(ca, max_certificates=2)
    signers = {vid: Signer(creds[vid], math.inf) for vid in ("cv0", "cv1", "cv2")}
    t = NOW

    def send(vid: str) -> Verified | Rejection:
        nonlocal t
        t += 0.01
        return v.verify(signers[vid].sign(prior(vid), t), t)

    assert send("cv0") and send("cv1")  # their certificates
    assert send("cv0")  # a digest: cv0 is the most recently used now
    assert send("cv2")  # a third certificate: cv1's goes
    assert send("cv0") and send("cv2")
    assert_rejected(send("cv1"), "unknown_certificate")


def test_the_replay_table_is_bounded_and_never_lets_a_replay_through(ca, creds) -> None:
    v = verifier(ca, max_replay=3)
    signer = Signer(creds["cv0"])
    sent = [(NOW + 0.01 * k, signer.sign(prior("cv0"), NOW + 0.01 * k)) for k in range(8)]
    assert all(v.verify(data, t) for t, data in sent)
    assert len(v._seen) <= 3 and len(v._expiry) == len(v._seen)
    for t, data in sent:  # forgotten or not, each is refused again
        assert_rejected(v.verify(data, t + 0.01), "replayed")


def test_the_replay_table_forgets_what_left_the_window(ca, creds) -> None:
    v = verifier(ca)
    signer = Signer(creds["cv0"])
    for k in range(200):  # 20 s at 10 Hz through a window of +-2 s
        t = NOW + 0.1 * k
        assert v.verify(signer.sign(prior("cv0"), t), t)
    assert len(v._seen) <= 2 * WINDOW_S / 0.1 + 2


# ------------------------------------------------------------------------------ configuration


def test_verifier_checks_its_ca_and_arguments(ca, creds) -> None:
    with pytest.raises(ConfigError, match="not validly self-signed"):
        Verifier(creds["cv0"].certificate, WINDOW_S)  # a vehicle's certificate is no CA's
    tampered = ca.certificate.model_copy(update={"valid_until": ca.certificate.valid_until + 1})
    with pytest.raises(ConfigError, match="not validly self-signed"):
        Verifier(tampered, WINDOW_S)
    for window in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="window_s"):
            Verifier(ca.certificate, window)
    with pytest.raises(ValueError, match="max_certificates"):
        Verifier(ca.certificate, WINDOW_S, max_certificates=0)
    with pytest.raises(TypeError, match="Certificate"):
        Verifier(ca.private_key.public_key(), WINDOW_S)  # type: ignore[arg-type]


def test_issue_cuts_validity_to_the_cas_and_checks_its_arguments(ca) -> None:
    cert = ca.certificate
    late = issue(ca, "cv0", 100 * 365 * 86400.0, NOW)
    assert late.certificate.valid_from == math.floor(NOW) and late.certificate.valid_until == cert.valid_until
    assert late.certificate.issuer == ca.digest and late.certificate.subject == "cv0"
    with pytest.raises(ValueError, match="misses the CA"):
        issue(ca, "cv0", 60.0, cert.valid_until + 10.0)
    with pytest.raises(ValueError, match="validity_s"):
        issue(ca, "cv0", 0.0, NOW)
    with pytest.raises(ValueError, match="not an id"):
        issue(ca, "cv 0", 60.0, NOW)
    with pytest.raises(ValueError, match="uint32"):
        make_ca("big", now=NOW, validity_s=1e12)


def test_certificate_encoding_and_digest(creds) -> None:
    cert = creds["cv0"].certificate
    raw = msgpack.unpackb(certificate_bytes(cert), strict_map_key=False)
    assert list(raw) == [83, 84, 85, 86, 87, 88] and raw[83] == "cv0" and len(raw[84]) == 33
    assert certificate_bytes(cert, signed=False) == msgpack.packb({k: raw[k] for k in list(raw)[:5]})
    assert len(certificate_bytes(cert)) == 132  # a 3-character subject
    assert creds["cv0"].digest != creds["cv1"].digest and len(creds["cv0"].digest) == 8


@pytest.mark.parametrize(
    ("change", "value"),
    [("signer_digest", b"\x01" * 7), ("signature", b"\x00" * 63), ("t_gen_us", 2**63), ("t_gen_us", 1.5)],
)
def test_a_secured_message_with_a_bad_field_is_invalid(creds, change: str, value) -> None:
    raw = msgpack.unpackb(Signer(creds["cv0"], math.inf).sign(b"x", NOW), strict_map_key=False)
    raw.pop(90, None)
    raw[91] = creds["cv0"].digest
    raw[{"signer_digest": 91, "signature": 88, "t_gen_us": 92}[change]] = value
    out = decode(msgpack.packb(raw), SecuredMessage)
    assert isinstance(out, Rejection) and out.reason == "invalid", out


def test_certificate_fields_are_checked() -> None:
    good = dict(
        subject="cv0",
        public_key=b"\x02" + bytes(32),
        valid_from=10,
        valid_until=20,
        issuer=bytes(8),
        signature=bytes(64),
    )
    Certificate(**good)
    for bad in ({"public_key": b"\x04" + bytes(32)}, {"valid_until": 5}, {"subject": "a/b"}, {"valid_from": -1}):
        with pytest.raises(ValueError):
            Certificate(**{**good, **bad})


# ------------------------------------------------------------------------------ files


def test_credentials_round_trip_through_files(tmp_path, ca, creds) -> None:
    key_path, cert_path = save_credentials(creds["cv0"], tmp_path)
    save_credentials(ca, tmp_path, CA_NAME)
    assert (key_path.name, cert_path.name) == ("cv0.key.pem", "cv0.cert.json")
    assert stat.S_IMODE(os.stat(key_path).st_mode) == 0o600
    back = load_credentials(tmp_path, "cv0")
    assert back.certificate == creds["cv0"].certificate and back.digest == creds["cv0"].digest
    assert load_certificate(tmp_path, CA_NAME) == ca.certificate
    v = Verifier(load_certificate(tmp_path, CA_NAME), WINDOW_S)
    assert v.verify(Signer(back).sign(prior("cv0"), NOW), NOW, "cv0")
    assert json.loads(cert_path.read_text())["subject"] == "cv0"


def test_missing_and_bad_files_are_configuration_errors(tmp_path, ca, creds) -> None:
    with pytest.raises(ConfigError, match=r"cv0\.key\.pem does not exist.*mapc keys init"):
        load_credentials(tmp_path / "nowhere", "cv0")
    key_path, cert_path = save_credentials(creds["cv0"], tmp_path)
    cert_path.unlink()
    with pytest.raises(ConfigError, match=r"certificate .*cv0\.cert\.json does not exist"):
        load_credentials(tmp_path, "cv0")

    save_credentials(creds["cv0"], tmp_path)
    cert_path.write_text("{not json")
    with pytest.raises(ConfigError, match=r"cv0\.cert\.json is not a certificate"):
        load_credentials(tmp_path, "cv0")
    cert_path.write_text(json.dumps({**json.loads(creds["cv0"].certificate.model_dump_json()), "issuer": "AAAA"}))
    with pytest.raises(ConfigError, match=r"is not a certificate: issuer"):
        load_certificate(tmp_path, "cv0")

    save_credentials(creds["cv0"], tmp_path)
    key_path.write_text("-----BEGIN PRIVATE KEY-----\nnonsense\n-----END PRIVATE KEY-----\n")
    with pytest.raises(ConfigError, match="not an unencrypted PEM private key"):
        load_credentials(tmp_path, "cv0")
    key_path.write_bytes(
        ed25519.Ed25519PrivateKey.generate().private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    with pytest.raises(ConfigError, match="not a P-256"):
        load_credentials(tmp_path, "cv0")
    save_credentials(Credentials(creds["cv1"].private_key, creds["cv0"].certificate), tmp_path, "cv0")
    with pytest.raises(ConfigError, match="do not match"):
        load_credentials(tmp_path, "cv0")


# ------------------------------------------------------------------------------ README recipe


def readme_recipe() -> str:
    text = README.read_text(encoding="utf-8")
    return next(b.split("```")[0] for b in text.split("```python")[1:] if "def open_signed" in b)


def test_readme_recipe_opens_our_signed_messages(ca, creds) -> None:
    namespace: dict = {}
    exec(readme_recipe(), namespace)  # noqa: S102 - the README's own code, run as a reader would
    ca_cert = msgpack.unpackb(certificate_bytes(ca.certificate), strict_map_key=False)
    payload = prior("cv0")
    data = Signer(creds["cv0"]).sign(payload, NOW)
    assert namespace["open_signed"](data, ca_cert) == payload
    assert namespace["digest"](msgpack.unpackb(certificate_bytes(creds["cv0"].certificate), strict_map_key=False)) == (
        creds["cv0"].digest
    )
    with pytest.raises(ValueError, match="bad signature"):
        namespace["open_signed"](flip(data, data.index(payload) + 3), ca_cert)
    other = issue(make_ca("other", now=NOW - 60), "cv0", 600.0, NOW - 60)
    with pytest.raises(ValueError, match="not our CA"):
        namespace["open_signed"](Signer(other).sign(payload, NOW), ca_cert)


# ------------------------------------------------------------------------------ CLI


def test_keys_init_writes_a_ca_and_the_vehicles_credentials(tmp_path, capsys) -> None:
    out = tmp_path / "keys"
    assert main(["keys", "init", "--out", str(out), "--vehicles", "cv0,cv1,rsu-1", "--validity-days", "2"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert sorted(doc["vehicles"]) == ["cv0", "cv1", "rsu-1"] and doc["dir"] == str(out)
    assert doc["valid_until"] - doc["valid_from"] == 2 * 86400 + 3600
    ca_cert = load_certificate(out, CA_NAME)
    assert certificate_digest(ca_cert).hex() == doc["ca"]["digest"] and ca_cert.subject == "mapc-ca"
    v = Verifier(ca_cert, WINDOW_S)
    t = doc["valid_from"] + 7200.0
    for vid, digest in doc["vehicles"].items():
        cred = load_credentials(out, vid)
        assert cred.digest.hex() == digest
        assert v.verify(Signer(cred).sign(prior(vid), t), t, vid)

    assert main(["keys", "init", "--out", str(out)]) == 2  # would replace cv0, cv1 and the CA
    err = capsys.readouterr().err.strip()
    assert err.startswith("mapc: configuration error:") and "--force" in err and len(err.splitlines()) == 1
    assert main(["keys", "init", "--out", str(out), "--count", "2", "--force"]) == 0
    assert sorted(json.loads(capsys.readouterr().out)["vehicles"]) == ["cv0", "cv1"]
    assert load_credentials(out, "cv1").certificate.issuer == certificate_digest(load_certificate(out, CA_NAME))


@pytest.mark.parametrize(
    "argv",
    [["--vehicles", "cv0,cv0"], ["--vehicles", "cv0,ca"], ["--vehicles", "a b"], ["--count", "0"],
     ["--validity-days", "0"], ["--vehicles", "cv0", "--count", "2"]],
)  # fmt: skip
def test_keys_init_refuses_bad_arguments(tmp_path, capsys, argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["keys", "init", "--out", str(tmp_path / "k"), *argv])
    assert exc.value.code == 2
    assert not (tmp_path / "k").exists()


def test_keys_init_refuses_a_validity_past_2106(tmp_path, capsys) -> None:
    assert main(["keys", "init", "--out", str(tmp_path), "--validity-days", "1e9"]) == 2
    assert "uint32" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_bench_security_prints_its_figures(capsys) -> None:
    assert main(["bench", "security", "--iterations", "3", "--objects", "8"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["iterations"] == 3 and doc["objects"] == 8
    for name in ("sign_us_p50", "verify_us_p50", "verify_full_us_p50", "verify_new_certificate_us_p50"):
        assert doc[name] > 0, name
    assert doc["bytes_added_digest"] == 95 and doc["bytes_added_full"] == 95 - 11 + 1 + 132
    assert doc["prior_bytes"] > 256 and doc["sign_over_ecdsa"] > 0


def test_bench_security_payload_sizes() -> None:
    small = bench_security(iterations=1, objects=0)
    assert small["prior_bytes"] < 256 and small["bytes_added_digest"] == 94  # bin8 for the payload
