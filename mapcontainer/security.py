"""Signed V2X messages, as IEEE 1609.2 / ETSI TS 103 097 sign them: the pure core (no network I/O).

A fleet CA (:func:`make_ca`) issues every vehicle a certificate for its P-256 key (:func:`issue`). A
vehicle's :class:`Signer` wraps each encoded message in a :class:`~schemas.models.SecuredMessage`: the
payload, the generation time, the signer (its full certificate about once a second, its 8-byte digest
otherwise) and an ECDSA P-256 signature. A receiver's :class:`Verifier` checks it and returns the
payload as :class:`Verified`, or a :class:`~schemas.codec.Rejection` with one of :data:`REASONS`
(counted in ``Verifier.rejected``); it never raises on bad input.

Byte strings signed (SHA-256 of each, ECDSA P-256, signatures 64 bytes ``r || s`` big-endian):

* a certificate: its canonical encoding without ``signature`` (:func:`certificate_bytes`), by the CA;
* a message: ``payload || t_gen_us (int64, big-endian) || digest of the signer's certificate``, by the
  vehicle, whether the message carries the certificate or only its digest.

A certificate's digest (1609.2's HashedId8) is the first 8 bytes of the SHA-256 of its whole
canonical encoding (:func:`certificate_digest`). Times are Unix time: the Signer's ``t_now``, the
Verifier's ``now`` and certificate validity are on one clock.

Credentials live in a directory (``mapc keys init``): ``NAME.key.pem`` (PKCS #8, unencrypted, mode
0600) and ``NAME.cert.json`` (the certificate, bytes as base64url), the CA's under the name ``ca``.
"""

from __future__ import annotations

import hashlib
import heapq
import math
import os
import re
import reprlib
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path

import msgpack
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature, encode_dss_signature
from pydantic import ValidationError

from schemas.codec import Rejection, decode, peek
from schemas.models import (
    DIGEST_BYTES,
    MAX_CERT_TIME_S,
    NAME_PATTERN,
    SCHEMA_VERSION,
    Certificate,
    SecuredMessage,
)
from schemas.tags import TAGS

from .config import ConfigError

__all__ = [
    "CA_NAME",
    "REASONS",
    "Credentials",
    "CredentialsMissing",
    "Signer",
    "Verified",
    "Verifier",
    "certificate_bytes",
    "certificate_digest",
    "fused_signers",
    "issue",
    "load_certificate",
    "load_credentials",
    "make_ca",
    "save_credentials",
    "service_signer",
    "unwrap",
    "write_fleet_keys",
]

REASONS = (
    "unsigned",  # not a SecuredMessage (a bare message, garbage, a broken envelope)
    "unknown_certificate",  # a digest whose certificate was not seen yet, or a certificate not from our CA
    "forged",  # a bad signature: the CA's on the certificate or the signer's on the message
    "expired",  # the signer's certificate (or our CA's) is not valid at the receiver's time
    "replayed",  # this (sender, generation time) was accepted before, or the time is outside the window
    "sender_mismatch",  # the payload's sender, the certificate's subject and the expected sender disagree
)

CA_NAME = "ca"  # file stem of the CA's credentials in a keys directory
SELF_SIGNED = bytes(DIGEST_BYTES)  # the issuer of a self-signed (CA) certificate
DEFAULT_CA_VALIDITY_S = 10 * 365 * 86400.0

_CURVE = ec.SECP256R1()
_ECDSA = ec.ECDSA(hashes.SHA256())
_CERT_FIELDS = ("subject", "public_key", "valid_from", "valid_until", "issuer", "signature")  # tag order
_CERT_TAGS = tuple(TAGS[f] for f in _CERT_FIELDS)
_MAX_ITEMS = 16  # maps and arrays in a SecuredMessage: six fields, a certificate of six (and room for new ones)
_NAME = re.compile(NAME_PATTERN)

_repr = reprlib.Repr()
_repr.maxlevel, _repr.maxstring, _repr.maxother = 2, 40, 40


# ------------------------------------------------------------------------------ primitives


def certificate_bytes(cert: Certificate, *, signed: bool = True) -> bytes:
    """The canonical encoding of ``cert``: a msgpack map of its fields keyed by tag, in tag order
    (what :func:`schemas.codec.encode` packs for the part); without ``signature`` when not ``signed``
    (the bytes the issuer signs)."""
    n = len(_CERT_FIELDS) if signed else len(_CERT_FIELDS) - 1
    return msgpack.packb({_CERT_TAGS[i]: getattr(cert, _CERT_FIELDS[i]) for i in range(n)}, use_bin_type=True)


def certificate_digest(cert: Certificate) -> bytes:
    """HashedId8 of ``cert``: the first 8 bytes of SHA-256 of its canonical encoding."""
    return hashlib.sha256(certificate_bytes(cert)).digest()[:DIGEST_BYTES]


def _message_tbs(payload: bytes, t_gen_us: int, digest: bytes) -> bytes:
    """The bytes a message signature covers: payload || t_gen_us (int64 big-endian) || signer digest."""
    return b"".join((payload, t_gen_us.to_bytes(8, "big", signed=True), digest))


def _sign(key: ec.EllipticCurvePrivateKey, data: bytes) -> bytes:
    """ECDSA P-256 over SHA-256 of ``data`` as 64 bytes r || s (not DER)."""
    r, s = decode_dss_signature(key.sign(data, _ECDSA))
    return r.to_bytes(32, "big") + s.to_bytes(32, "big")


def _valid(key: ec.EllipticCurvePublicKey, signature: bytes, data: bytes) -> bool:
    """Whether ``signature`` (r || s) is ``key``'s ECDSA P-256 signature of ``data``; never raises."""
    try:
        der = encode_dss_signature(int.from_bytes(signature[:32], "big"), int.from_bytes(signature[32:], "big"))
        key.verify(der, data, _ECDSA)
    except (InvalidSignature, ValueError):
        return False
    return True


def _compressed(key: ec.EllipticCurvePublicKey) -> bytes:
    return key.public_bytes(serialization.Encoding.X962, serialization.PublicFormat.CompressedPoint)


# ------------------------------------------------------------------------------ credentials


@dataclass(frozen=True)
class Credentials:
    """A private key and the certificate of its public key: a vehicle's, or the CA's (self-signed)."""

    private_key: ec.EllipticCurvePrivateKey
    certificate: Certificate

    @property
    def subject(self) -> str:
        return self.certificate.subject

    @property
    def digest(self) -> bytes:
        """The certificate's digest (HashedId8)."""
        return certificate_digest(self.certificate)


def _certify(key, subject: str, valid_from: int, valid_until: int, issuer: bytes, signer) -> Certificate:
    if not isinstance(subject, str) or not _NAME.match(subject):
        raise ValueError(f"subject {subject!r} is not an id (letters, digits, '_' or '-', 1-64)")
    unsigned = Certificate.model_construct(
        subject=subject,
        public_key=_compressed(key.public_key()),
        valid_from=valid_from,
        valid_until=valid_until,
        issuer=issuer,
    )
    tbs = certificate_bytes(unsigned, signed=False)
    return Certificate(**unsigned.model_dump(), signature=_sign(signer, tbs))


def _validity(now: float, validity_s: float) -> tuple[int, int]:
    """Whole seconds from ``now`` (rounded down) to ``now + validity_s``."""
    if not (math.isfinite(now) and math.isfinite(validity_s)) or validity_s <= 0:
        raise ValueError(f"need a finite now and validity_s > 0, got now={now!r}, validity_s={validity_s!r}")
    return math.floor(now), math.floor(now + validity_s)


def make_ca(name: str, *, now: float | None = None, validity_s: float = DEFAULT_CA_VALIDITY_S) -> Credentials:
    """A fresh fleet CA: a P-256 key and its self-signed certificate (``issuer`` all zero), valid for
    ``validity_s`` from ``now`` (Unix time; default the current time)."""
    valid_from, valid_until = _validity(time.time() if now is None else now, validity_s)
    if valid_from < 0 or valid_until > MAX_CERT_TIME_S:
        raise ValueError(f"validity {valid_from}..{valid_until} is outside 0..{MAX_CERT_TIME_S} (Unix s, uint32)")
    key = ec.generate_private_key(_CURVE)
    return Credentials(key, _certify(key, name, valid_from, valid_until, SELF_SIGNED, key))


def issue(ca: Credentials, subject_id: str, validity_s: float, now: float) -> Credentials:
    """A fresh P-256 key for ``subject_id`` and its certificate signed by ``ca``, valid from ``now``
    (Unix time, rounded down to the second) for ``validity_s`` seconds, cut to the CA's own validity.

    ValueError for a bad id, a non-positive validity or one that misses the CA's validity entirely."""
    valid_from, valid_until = _validity(now, validity_s)
    ca_cert = ca.certificate
    valid_from, valid_until = max(valid_from, ca_cert.valid_from), min(valid_until, ca_cert.valid_until)
    if valid_until < valid_from:
        raise ValueError(
            f"{subject_id}: validity from {now:.0f} s for {validity_s:g} s misses the CA's "
            f"{ca_cert.valid_from}..{ca_cert.valid_until}"
        )
    key = ec.generate_private_key(_CURVE)
    return Credentials(key, _certify(key, subject_id, valid_from, valid_until, ca.digest, ca.private_key))


def _paths(directory: Path, name: str) -> tuple[Path, Path]:
    return Path(directory) / f"{name}.key.pem", Path(directory) / f"{name}.cert.json"


def save_credentials(credentials: Credentials, directory: str | Path, name: str | None = None) -> tuple[Path, Path]:
    """Write ``NAME.key.pem`` (PKCS #8, unencrypted, mode 0600) and ``NAME.cert.json`` into ``directory``
    (created if needed); ``name`` defaults to the certificate's subject. Returns the two paths."""
    name = credentials.subject if name is None else name
    if not _NAME.match(name):
        raise ValueError(f"name {name!r} is not an id (letters, digits, '_' or '-', 1-64)")
    Path(directory).mkdir(parents=True, exist_ok=True)
    key_path, cert_path = _paths(Path(directory), name)
    pem = credentials.private_key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(pem)
    os.chmod(key_path, 0o600)  # an existing file keeps its mode through os.open
    cert_path.write_text(credentials.certificate.model_dump_json(indent=2) + "\n", encoding="utf-8")
    return key_path, cert_path


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist (`mapc keys init --out DIR` writes one)") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {path}: {exc.strerror}") from None


def load_certificate(directory: str | Path, name: str) -> Certificate:
    """The certificate ``NAME.cert.json`` in ``directory``; ConfigError if it is missing or bad."""
    path = _paths(Path(directory), name)[1]
    text = _read(path, "certificate")
    try:
        return Certificate.model_validate_json(text)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"{path} is not a certificate: {where + ': ' if where else ''}{first['msg']}") from None


def load_credentials(directory: str | Path, name: str) -> Credentials:
    """``NAME.key.pem`` and ``NAME.cert.json`` from ``directory`` (``name`` a vehicle id or ``ca``).

    ConfigError when a file is missing or unreadable, the key is not a P-256 private key in PEM, the
    certificate does not validate, or the certificate is not the key's."""
    key_path = _paths(Path(directory), name)[0]
    pem = _read(key_path, "private key")
    cert = load_certificate(directory, name)
    try:
        key = serialization.load_pem_private_key(pem, password=None)
    except (ValueError, TypeError) as exc:  # not PEM, encrypted, or an unsupported key
        raise ConfigError(f"{key_path} is not an unencrypted PEM private key: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or not isinstance(key.curve, ec.SECP256R1):
        raise ConfigError(f"{key_path} holds a {type(key).__name__}, not a P-256 (secp256r1) key")
    if _compressed(key.public_key()) != cert.public_key:
        raise ConfigError(f"{key_path} and {_paths(Path(directory), name)[1]} do not match: another key's certificate")
    return Credentials(key, cert)


# ------------------------------------------------------------------------------ signing


class Signer:
    """Signs a vehicle's messages: ``sign(payload, t_now)`` -> an encoded SecuredMessage.

    The full certificate goes with the first message and then whenever ``full_cert_every_s`` has
    passed since it last went (or the clock went back); the 8-byte digest with the others. Generation
    times are whole microseconds and strictly increasing (one microsecond past the previous when
    ``t_now`` did not advance), so two messages of one instant are never taken for a replay.
    """

    def __init__(self, credentials: Credentials, full_cert_every_s: float = 1.0) -> None:
        if not full_cert_every_s >= 0:  # inf: the certificate goes with the first message only
            raise ValueError(f"full_cert_every_s must be >= 0, got {full_cert_every_s!r}")
        self.credentials = credentials
        self.full_cert_every_s = float(full_cert_every_s)
        self._key = credentials.private_key
        self._digest = credentials.digest
        self._cert_map = msgpack.unpackb(certificate_bytes(credentials.certificate), strict_map_key=False)
        self._last_full: float | None = None
        self._last_us: int | None = None

    def sign(self, payload: bytes, t_now: float) -> bytes:
        """The encoded SecuredMessage of ``payload`` (an encoded message) generated at ``t_now`` (Unix s)."""
        if not isinstance(payload, bytes | bytearray | memoryview):
            raise TypeError(f"payload is {type(payload).__name__}, not bytes")
        if not math.isfinite(t_now):
            raise ValueError(f"t_now must be finite, got {t_now!r}")
        payload = bytes(payload)
        t_us = round(t_now * 1e6)
        if self._last_us is not None and t_us <= self._last_us:
            t_us = self._last_us + 1
        self._last_us = t_us
        last = self._last_full
        full = last is None or t_now - last >= self.full_cert_every_s or t_now < last
        if full:
            self._last_full = t_now
        signature = _sign(self._key, _message_tbs(payload, t_us, self._digest))
        wire = {_T_VERSION: SCHEMA_VERSION, _T_PAYLOAD: payload}
        if full:
            wire[_T_CERT] = self._cert_map
        else:
            wire[_T_DIGEST] = self._digest
        wire[_T_TGEN] = t_us
        wire[_T_SIG] = signature
        return msgpack.packb(wire, use_bin_type=True)


# In SecuredMessage's field order, as schemas.codec.encode packs it (a test checks the bytes agree).
_T_VERSION, _T_PAYLOAD, _T_CERT, _T_DIGEST, _T_TGEN, _T_SIG = (
    TAGS[f] for f in ("schema_version", "payload", "certificate", "signer_digest", "t_gen_us", "signature")
)


VERIFY_WINDOW_S = 5.0  # services: a signed message generated longer ago (or ahead) than this is refused as replayed
KEYS_SKEW_S = 3600.0  # write_fleet_keys: certificates start this long before now (clocks of other machines)


# they sign truth, metrics and fused state, and every service its health status
SERVICE_SIGNERS = ("world", "evaluator", "host", "host-standby", "channel", "recorder", "router")


class CredentialsMissing(ConfigError):
    """A keys directory without credentials for this id (keys made for fewer services)."""


def service_signer(directory: str | Path, sid: str) -> Signer:
    """The signer of service ``sid``'s health status: its credentials in ``directory``, the full certificate
    with every message (a health query is answered to a verifier that has seen none of the service's
    messages before). CredentialsMissing when ``directory`` holds none for ``sid``; ConfigError when they
    are there but bad."""
    key_path, cert_path = _paths(Path(directory), sid)
    if not key_path.exists() and not cert_path.exists():
        raise CredentialsMissing(f"{directory} holds no credentials for {sid!r} (`mapc keys init` names the services)")
    return Signer(load_credentials(directory, sid), full_cert_every_s=0.0)


def write_fleet_keys(
    out: Path,
    vehicles: list[str],
    validity_s: float,
    ca_name: str = "fleet-ca",
    *,
    force: bool = False,
    services: tuple[str, ...] | list[str] = SERVICE_SIGNERS,
) -> dict:
    """A test CA and credentials for ``vehicles`` and ``services`` in ``out`` (``mapc keys init``, and a fleet
    run's own keys): the world signs its truth, the evaluator its metrics, a host (by its id) its fused state.

    Returns what was written (the CA's and each certificate's digest, the validity). A directory that
    already holds credentials of these names is a ConfigError unless ``force``.
    """
    services = [x for x in dict.fromkeys(services) if x not in vehicles]
    names = [CA_NAME, *vehicles, *services]
    existing = [p.name for n in names for p in _paths(Path(out), n) if p.exists()]
    if existing and not force:
        more = " ..." if len(existing) > 4 else ""
        raise ConfigError(f"{out} already holds {', '.join(existing[:4])}{more}: keys of a run (--force replaces them)")
    now = time.time() - KEYS_SKEW_S
    try:
        ca = make_ca(ca_name, now=now, validity_s=validity_s + KEYS_SKEW_S)
        vehicle_creds = [issue(ca, vid, validity_s + KEYS_SKEW_S, now) for vid in vehicles]
        service_creds = [issue(ca, sid, validity_s + KEYS_SKEW_S, now) for sid in services]
    except ValueError as exc:  # a validity past 2106 (Unix seconds in 32 bits), a bad name
        raise ConfigError(f"keys for {vehicles + services}: {exc}") from None
    save_credentials(ca, out, CA_NAME)
    for creds in vehicle_creds + service_creds:
        save_credentials(creds, out)
    cert = ca.certificate
    return {
        "dir": str(out),
        "ca": {"subject": cert.subject, "digest": ca.digest.hex()},
        "valid_from": cert.valid_from,
        "valid_until": cert.valid_until,
        "vehicles": {c.subject: c.digest.hex() for c in vehicle_creds},
        "services": {c.subject: c.digest.hex() for c in service_creds},
    }


STANDBY_SUFFIX = "-standby"  # a warm standby host's id: its host's id and this


def fused_signers(host_id: str) -> frozenset[str]:
    """Who may sign the fused state published on host ``host_id``'s key: the host, and its warm standby."""
    return frozenset((host_id, host_id + STANDBY_SUFFIX))


def unwrap(
    data: bytes, verifier: Verifier | None, now: float, senders: str | frozenset[str] | None = None
) -> bytes | Rejection:
    """What a consumer reads of a message that may be signed: with a ``verifier`` (the fleet's CA), the
    verified inner message, or the Rejection (an unsigned message is refused, and so is one whose verified
    sender is not ``senders``: an id, or a set of ids); without one, the inner message unverified, or
    ``data`` itself if it is not signed."""
    if verifier is None:
        return inner_payload(data)
    one = senders if isinstance(senders, str) else None
    out = verifier.verify(data, now, expected_sender=one)
    if isinstance(out, Rejection):
        return out
    if senders is not None and one is None and out.sender not in senders:
        return Rejection("sender_mismatch", f"signed by {out.sender}, not by one of {sorted(senders)}")
    return out.payload


def inner_payload(data: bytes) -> bytes:
    """The message inside a SecuredMessage, unverified (for counting and routing); ``data`` itself if it is
    not one. Whoever acts on the content verifies first (:class:`Verifier`)."""
    inner = peek(data).get("payload")
    return inner if isinstance(inner, bytes) else data


# ------------------------------------------------------------------------------ verifying


@dataclass(frozen=True, slots=True)
class Verified:
    """A message that passed every check: its payload (an encoded message), sender and generation time."""

    payload: bytes
    sender: str
    t_gen: float  # Unix time (s)


@dataclass(frozen=True, slots=True)
class _Known:
    """A verified certificate, ready to check messages: its loaded key and its validity within the CA's."""

    subject: str
    key: ec.EllipticCurvePublicKey
    digest: bytes
    valid_from: int
    valid_until: int


class Verifier:
    """Checks SecuredMessages signed by certificates of one CA: ``verify(data, now, expected_sender)``.

    In order: the bytes are a SecuredMessage (else ``unsigned``); its signer is a certificate of our CA
    (a digest must name one seen in full before: else ``unknown_certificate``) whose CA signature holds
    (else ``forged``); the certificate is valid at ``now`` (else ``expired``); the generation time is
    within ``window_s`` of ``now`` (else ``replayed``); the message signature holds (else ``forged``);
    the payload's ``sender``, the certificate's subject and ``expected_sender`` (when given) agree (else
    ``sender_mismatch``); the (sender, generation time) was not accepted before (else ``replayed``).

    Verified certificates are kept by digest, the ``max_certificates`` last used (LRU), with their
    public keys loaded: a message naming its signer by digest costs one signature check. Accepted
    (sender, generation time) pairs are kept while inside the window, at most ``max_replay`` of them:
    past that the oldest go, and every generation time up to the newest of those gone is refused as a
    replay from then on (never an accepted replay; under a flood, a late message may be refused).
    """

    def __init__(
        self, ca: Certificate, window_s: float, *, max_certificates: int = 4096, max_replay: int = 65536
    ) -> None:
        if not isinstance(ca, Certificate):
            raise TypeError(f"ca is {type(ca).__name__}, not the CA's Certificate")
        if not math.isfinite(window_s) or window_s <= 0:
            raise ValueError(f"window_s must be finite and > 0, got {window_s!r}")
        if max_certificates < 1 or max_replay < 1:
            raise ValueError(f"max_certificates and max_replay must be >= 1, got {max_certificates}, {max_replay}")
        try:
            ca_key = ec.EllipticCurvePublicKey.from_encoded_point(_CURVE, ca.public_key)
        except ValueError:
            raise ConfigError(f"CA certificate {ca.subject}: its public key is not a P-256 point") from None
        if ca.issuer != SELF_SIGNED or not _valid(ca_key, ca.signature, certificate_bytes(ca, signed=False)):
            raise ConfigError(f"CA certificate {ca.subject} is not validly self-signed")
        self.ca = ca
        self.window_s = float(window_s)
        self.max_certificates = int(max_certificates)
        self.max_replay = int(max_replay)
        self.rejected: Counter[str] = Counter()
        self.accepted = 0
        self._ca_key = ca_key
        self._ca_digest = certificate_digest(ca)
        self._window_us = round(self.window_s * 1e6)
        self._known: OrderedDict[bytes, _Known] = OrderedDict()
        self._bad: OrderedDict[bytes, tuple[str, str]] = OrderedDict()  # digest -> refusal: a forgery costs one check
        self._seen: set[tuple[str, int]] = set()
        self._expiry: list[tuple[int, str]] = []  # heap of the generation times in _seen
        self._floor_us: float = -math.inf  # generation times at or below it are refused

    def verify(
        self, data: bytes, now: float, expected_sender: str | None = None, *, new_certificates: bool = True
    ) -> Verified | Rejection:
        """``data`` checked at ``now`` (Unix s) against ``expected_sender`` (from the key, or None).

        Cheapest first: the outer message is parsed with every map and array bounded (its payload stays
        bytes, decoded by nobody before the signature holds); the signer must be a known certificate or
        a new one of our CA (``new_certificates=False``: a certificate not verified before is refused as
        ``unknown_certificate`` without checking the CA's signature, for traffic under a flood); the
        validity, the time window and the replay table are checked before the one ECDSA verification."""
        msg = decode(data, SecuredMessage, max_items=_MAX_ITEMS)
        if isinstance(msg, Rejection):
            return self._reject("unsigned", f"not a SecuredMessage ({msg.reason}: {msg.detail})")
        if msg.certificate is not None:
            if not new_certificates and certificate_digest(msg.certificate) not in self._known:
                return self._reject(
                    "unknown_certificate", f"{msg.certificate.subject}: a new certificate under a flood"
                )
            known = self._learn(msg.certificate)
            if isinstance(known, Rejection):
                return known
        else:
            known = self._known.get(msg.signer_digest)
            if known is None:
                return self._reject("unknown_certificate", f"digest {msg.signer_digest.hex()} not seen in full yet")
            self._known.move_to_end(msg.signer_digest)
        if not known.valid_from <= now <= known.valid_until:
            return self._reject(
                "expired", f"{known.subject}: valid {known.valid_from}..{known.valid_until}, now {now:.0f}"
            )
        t_us = msg.t_gen_us
        now_us = now * 1e6
        if abs(t_us - now_us) > self._window_us:
            return self._reject(
                "replayed",
                f"{known.subject}: generated {(t_us - now_us) / 1e6:+.3f} s from now (window +-{self.window_s:g} s)",
            )
        if (known.subject, t_us) in self._seen or t_us <= self._floor_us:  # a replay costs no ECDSA
            return self._reject("replayed", f"{known.subject}: generation time {t_us} us seen before")
        if not _valid(known.key, msg.signature, _message_tbs(msg.payload, t_us, known.digest)):
            return self._reject("forged", f"bad signature on a message signed as {known.subject}")
        inner = peek(msg.payload).get("sender")
        if inner != known.subject or (expected_sender is not None and expected_sender != known.subject):
            return self._reject(
                "sender_mismatch",
                f"payload sender {_repr.repr(inner)}, certificate {known.subject}, key {_repr.repr(expected_sender)}",
            )
        if not self._fresh(known.subject, t_us, now_us):
            return self._reject("replayed", f"{known.subject}: generation time {t_us} us seen before")
        self.accepted += 1
        return Verified(msg.payload, known.subject, t_us / 1e6)

    def _reject(self, reason: str, detail: str) -> Rejection:
        self.rejected[reason] += 1
        return Rejection(reason, detail[:200])

    def _learn(self, cert: Certificate) -> _Known | Rejection:
        """The cached entry of ``cert``, verified and added first if it is new."""
        digest = certificate_digest(cert)
        known = self._known.get(digest)
        if known is not None:
            self._known.move_to_end(digest)
            return known
        bad = self._bad.get(digest)
        if bad is not None:
            self._bad.move_to_end(digest)
            return self._reject(*bad)
        if cert.issuer != self._ca_digest:
            return self._reject(
                "unknown_certificate",
                f"{cert.subject}: issued by {cert.issuer.hex()}, not our CA {self._ca_digest.hex()}",
            )
        if not _valid(self._ca_key, cert.signature, certificate_bytes(cert, signed=False)):
            return self._refuse_certificate(digest, "forged", f"{cert.subject}: the CA's signature does not hold")
        try:
            key = ec.EllipticCurvePublicKey.from_encoded_point(_CURVE, cert.public_key)
        except ValueError:
            return self._refuse_certificate(digest, "forged", f"{cert.subject}: the certified key is not a P-256 point")
        valid_from, valid_until = max(cert.valid_from, self.ca.valid_from), min(cert.valid_until, self.ca.valid_until)
        known = _Known(cert.subject, key, digest, valid_from, valid_until)
        self._known[digest] = known
        if len(self._known) > self.max_certificates:
            self._known.popitem(last=False)
        return known

    def _refuse_certificate(self, digest: bytes, reason: str, detail: str) -> Rejection:
        """Refuse a certificate and remember it (bounded like the known ones), so that sending the same
        forgery again costs a hash, not a signature check."""
        self._bad[digest] = (reason, detail)
        if len(self._bad) > self.max_certificates:
            self._bad.popitem(last=False)
        return self._reject(reason, detail)

    def _fresh(self, sender: str, t_us: int, now_us: float) -> bool:
        """Record (sender, t_us) unless it is a replay; forget what fell out of the window."""
        key = (sender, t_us)
        if t_us <= self._floor_us or key in self._seen:
            return False
        self._seen.add(key)
        heapq.heappush(self._expiry, (t_us, sender))
        horizon = now_us - self._window_us
        while self._expiry and (self._expiry[0][0] < horizon or len(self._seen) > self.max_replay):
            t_old, s_old = heapq.heappop(self._expiry)
            self._seen.discard((s_old, t_old))
            self._floor_us = max(self._floor_us, t_old)
        return True
