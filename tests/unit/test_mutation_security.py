"""mapcontainer.security: the decisions a receiver gets at the edges (a CA-signed certificate of no P-256 key,
the LRU refresh of a certificate sent again in full, same-instant signing, the end of a validity)."""

from __future__ import annotations

import math

import pytest
from cryptography.hazmat.primitives.asymmetric import ec

from mapcontainer import security as sec
from mapcontainer.security import Credentials, Signer, Verified, Verifier, certificate_bytes, issue, make_ca
from schemas import Certificate, SecuredMessage, decode

from .test_security import NOW, WINDOW_S, assert_rejected, prior


@pytest.fixture(scope="module")
def ca() -> Credentials:
    return make_ca("fleet-ca", now=NOW - 3600, validity_s=7200.0)  # valid NOW-3600 .. NOW+3600


@pytest.fixture(scope="module")
def creds(ca: Credentials) -> dict[str, Credentials]:
    return {vid: issue(ca, vid, 86400.0, NOW - 600) for vid in ("cv0", "cv1", "cv2")}


def _ca_signed(ca: Credentials, subject: str, public_key: bytes, valid_from: int, valid_until: int) -> Certificate:
    unsigned = Certificate.model_construct(
        subject=subject, public_key=public_key, valid_from=valid_from, valid_until=valid_until, issuer=ca.digest
    )
    sig = sec._sign(ca.private_key, certificate_bytes(unsigned, signed=False))
    return Certificate(**unsigned.model_dump(), signature=sig)


def test_a_ca_signed_certificate_whose_key_is_not_a_point_is_forged(ca) -> None:
    not_a_point = b"\x02" + b"\xff" * 32  # x beyond the field prime
    cert = _ca_signed(ca, "cv5", not_a_point, int(NOW) - 60, int(NOW) + 60)
    signer = Signer(Credentials(ec.generate_private_key(ec.SECP256R1()), cert), 0.0)
    v = Verifier(ca.certificate, WINDOW_S)
    out = v.verify(signer.sign(prior("cv5"), NOW), NOW)
    assert_rejected(out, "forged")
    assert "not a P-256 point" in out.detail
    assert_rejected(v.verify(signer.sign(prior("cv5"), NOW + 0.1), NOW + 0.1), "forged")  # remembered
    assert v.rejected == {"forged": 2} and v.accepted == 0


def test_a_certificate_sent_again_in_full_is_refreshed_in_the_cache(ca, creds) -> None:
    v = Verifier(ca.certificate, WINDOW_S, max_certificates=2)
    signers = {vid: Signer(creds[vid], 0.0) for vid in ("cv0", "cv1", "cv2")}  # every message in full
    t = NOW

    def send(vid: str) -> Verified | sec.Rejection:
        nonlocal t
        t += 0.01
        return v.verify(signers[vid].sign(prior(vid), t), t)

    assert send("cv0") and send("cv1") and send("cv0")  # cv0's certificate again: most recently used
    assert send("cv2")  # evicts cv1's, not cv0's
    digest_only = Signer(creds["cv0"], math.inf)
    digest_only.sign(prior("cv0"), t)  # its first message carries the certificate: not sent
    t += 0.01
    assert isinstance(v.verify(digest_only.sign(prior("cv0"), t), t), Verified)
    lost = Signer(creds["cv1"], math.inf)
    lost.sign(prior("cv1"), t)
    t += 0.01
    assert_rejected(v.verify(lost.sign(prior("cv1"), t), t), "unknown_certificate")
    assert len(v._known) == 2


def test_a_full_certificate_goes_again_at_the_same_instant_when_the_period_is_zero(creds) -> None:
    def full(signer: Signer, t: float) -> bool:
        return decode(signer.sign(b"x", t), SecuredMessage).certificate is not None

    s = Signer(creds["cv0"], 0.0)
    assert [full(s, NOW) for _ in range(3)] == [True, True, True]
    s = Signer(creds["cv0"])  # default: once a second
    assert s.full_cert_every_s == 1.0
    assert [full(s, t) for t in (NOW, NOW, NOW + 0.999, NOW + 1.0, NOW + 1.5, NOW + 2.0)] == [
        True,
        False,
        False,
        True,
        False,
        True,
    ]
    with pytest.raises(ValueError, match="full_cert_every_s must be >= 0"):
        Signer(creds["cv0"], float("nan"))


def test_generation_time_is_rounded_to_the_microsecond(ca, creds) -> None:
    s = Signer(creds["cv0"], 0.0)
    t_us = [decode(s.sign(b"x", t), SecuredMessage).t_gen_us for t in (100.0000013, 100.0000027)]
    assert t_us == [100_000_001, 100_000_003]  # rounded, not truncated
    with pytest.raises(ValueError, match="t_now must be finite"):
        s.sign(b"x", math.nan)
    with pytest.raises(TypeError, match="not bytes"):
        s.sign("x", NOW)  # type: ignore[arg-type]


def test_a_vehicle_certificate_is_valid_to_its_last_second_and_not_after(ca) -> None:
    cv = issue(ca, "cv3", 100.0, NOW)
    end = cv.certificate.valid_until
    assert (cv.certificate.valid_from, end) == (math.floor(NOW), math.floor(NOW) + 100)
    v = Verifier(ca.certificate, WINDOW_S)
    s = Signer(cv, 0.0)
    assert isinstance(v.verify(s.sign(prior("cv3"), end), end), Verified)
    out = v.verify(s.sign(prior("cv3"), end + 0.5), end + 0.5)
    assert_rejected(out, "expired")
    assert out.detail == f"cv3: valid {math.floor(NOW)}..{end}, now {end + 0.5:.0f}"
    start = cv.certificate.valid_from
    assert isinstance(v.verify(Signer(cv, 0.0).sign(prior("cv3"), start), start), Verified)  # its first second
    assert_rejected(v.verify(Signer(cv, 0.0).sign(prior("cv3"), start - 0.5), start - 0.5), "expired")


def test_a_vehicle_certificate_is_cut_to_the_cas_validity(ca) -> None:
    ca_end = ca.certificate.valid_until
    cv = issue(ca, "cv4", 86400.0, NOW)
    assert cv.certificate.valid_until == ca_end  # issue cuts it
    long = _ca_signed(ca, "cv6", cv.certificate.public_key, int(NOW) - 10, ca_end + 1000)  # a CA that did not cut
    v = Verifier(ca.certificate, WINDOW_S)
    s = Signer(Credentials(cv.private_key, long), 0.0)
    assert isinstance(v.verify(s.sign(prior("cv6"), ca_end), ca_end), Verified)
    assert_rejected(v.verify(s.sign(prior("cv6"), ca_end + 1), ca_end + 1), "expired")  # the CA's end holds


def test_issue_validity_edges(ca) -> None:
    start = ca.certificate.valid_from
    cv = issue(ca, "cv7", 10.0, start - 5.0)  # from before the CA: starts with the CA
    assert (cv.certificate.valid_from, cv.certificate.valid_until) == (start, start + 5)
    one = issue(ca, "cv8", 1.0, float(ca.certificate.valid_until))  # the CA's last second: still issued
    assert one.certificate.valid_from == one.certificate.valid_until == ca.certificate.valid_until
    with pytest.raises(ValueError, match="misses the CA's"):
        issue(ca, "cv9", 10.0, ca.certificate.valid_until + 1.0)
    with pytest.raises(ValueError, match="validity_s > 0"):
        issue(ca, "cv9", 0.0, NOW)
    assert cv.certificate.issuer == ca.digest and cv.subject == "cv7" and len(cv.digest) == 8


def test_make_ca_defaults_and_limits() -> None:
    c = make_ca("x-ca", now=1000.7)
    assert (c.certificate.valid_from, c.certificate.valid_until) == (1000, 1000 + 10 * 365 * 86400)
    assert c.certificate.issuer == bytes(8)
    assert make_ca("y", now=0.0, validity_s=1.0).certificate.valid_from == 0
    with pytest.raises(ValueError, match="outside 0"):
        make_ca("z", now=-1.0, validity_s=10.0)
    with pytest.raises(ValueError, match="outside 0"):
        make_ca("z", now=float(2**32 - 10), validity_s=20.0)
    with pytest.raises(ValueError, match="is not an id"):
        make_ca("not an id", now=NOW)


def test_verifier_limits(ca) -> None:
    v = Verifier(ca.certificate, 0.5)
    assert (v.window_s, v.max_certificates, v.max_replay) == (0.5, 4096, 65536)
    assert Verifier(ca.certificate, 1.0, max_certificates=1, max_replay=1).max_replay == 1
    for kw in ({"max_certificates": 0}, {"max_replay": 0}):
        with pytest.raises(ValueError, match="must be >= 1"):
            Verifier(ca.certificate, 1.0, **kw)
    for w in (0.0, math.inf, -1.0):
        with pytest.raises(ValueError, match="window_s"):
            Verifier(ca.certificate, w)


def test_the_window_edge(ca, creds) -> None:
    v = Verifier(ca.certificate, 0.5)
    s = Signer(creds["cv1"], 0.0)
    assert isinstance(v.verify(s.sign(prior("cv1"), NOW), NOW + 0.5), Verified)  # exactly the window: accepted
    out = v.verify(s.sign(prior("cv1"), NOW + 1.0), NOW + 1.5 + 1e-3)
    assert_rejected(out, "replayed")
    assert out.detail == "cv1: generated -0.501 s from now (window +-0.5 s)"


def test_credentials_files_messages_name_what_is_wrong(tmp_path, ca, creds) -> None:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    from mapcontainer.config import ConfigError

    nested = tmp_path / "a" / "b"
    key_path, cert_path = sec.save_credentials(creds["cv0"], nested)  # parents created
    assert key_path.parent == nested and sec.load_credentials(nested, "cv0").subject == "cv0"
    key_path.unlink()
    with pytest.raises(ConfigError, match=r"^private key .*cv0\.key\.pem does not exist"):
        sec.load_credentials(nested, "cv0")
    key_path.write_bytes(
        ed25519.Ed25519PrivateKey.generate().private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    with pytest.raises(ConfigError, match=r"cv0\.key\.pem holds a Ed25519PrivateKey, not a P-256"):
        sec.load_credentials(nested, "cv0")
    sec.save_credentials(Credentials(creds["cv1"].private_key, creds["cv0"].certificate), nested, "cv0")
    with pytest.raises(ConfigError, match=r"cv0\.key\.pem and .*cv0\.cert\.json do not match"):
        sec.load_credentials(nested, "cv0")
    with pytest.raises(ValueError, match="is not an id"):
        sec.save_credentials(creds["cv0"], nested, "not an id")


def test_write_fleet_keys_defaults(tmp_path) -> None:
    doc = sec.write_fleet_keys(tmp_path, ["cv0"], 3600.0)
    ca_cert = sec.load_certificate(tmp_path, sec.CA_NAME)
    assert ca_cert.subject == "fleet-ca" and doc["ca"] == {
        "subject": "fleet-ca",
        "digest": sec.certificate_digest(ca_cert).hex(),
    }
    assert doc["valid_until"] - doc["valid_from"] == 3600 + int(sec.KEYS_SKEW_S)
    assert doc["vehicles"] == {"cv0": sec.load_credentials(tmp_path, "cv0").digest.hex()}


def test_inner_payload(creds) -> None:
    payload = prior("cv0")
    assert sec.inner_payload(Signer(creds["cv0"]).sign(payload, NOW)) == payload
    assert sec.inner_payload(payload) == payload  # not a SecuredMessage: itself
    assert sec.inner_payload(b"\xc1garbage") == b"\xc1garbage"


def test_a_ca_may_be_valid_to_the_last_uint32_second() -> None:
    from schemas.models import MAX_CERT_TIME_S

    c = make_ca("edge-ca", now=float(MAX_CERT_TIME_S - 10), validity_s=10.0)
    assert c.certificate.valid_until == MAX_CERT_TIME_S


def test_a_ca_certificate_whose_key_is_not_a_point_is_a_configuration_error(ca) -> None:
    from mapcontainer.config import ConfigError

    bad = ca.certificate.model_copy(update={"public_key": b"\x02" + b"\xff" * 32})
    with pytest.raises(ConfigError, match="CA certificate fleet-ca: its public key is not a P-256 point"):
        Verifier(bad, WINDOW_S)


def test_the_refused_certificates_kept_are_bounded_by_max_certificates(ca) -> None:
    v = Verifier(ca.certificate, WINDOW_S, max_certificates=2)
    for k in range(3):
        cert = _ca_signed(ca, f"cv{k}", b"\x02" + b"\xff" * 32, int(NOW) - 60, int(NOW) + 60)
        signer = Signer(Credentials(ec.generate_private_key(ec.SECP256R1()), cert), 0.0)
        assert_rejected(v.verify(signer.sign(prior(f"cv{k}"), NOW + k), NOW + k), "forged")
        assert len(v._bad) == min(k + 1, 2)
