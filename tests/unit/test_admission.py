"""Per-sender admission: a token bucket per sender, a bounded table of senders."""

from __future__ import annotations

import pytest

from mapcontainer.admission import Admission


def test_a_sender_gets_its_burst_then_its_rate() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    assert [a.admit("cv1", 0.0) for _ in range(22)] == [None] * 20 + ["flood", "flood"]
    assert a.admit("cv1", 0.05) is None  # 0.05 s at 20 Hz: one token back
    assert a.admit("cv1", 0.05) == "flood"
    assert a.refused() == {"cv1": 3}


def test_nominal_traffic_is_never_refused() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    assert all(a.admit("cv0", 0.1 * k) is None for k in range(1000))  # 10 Hz for 100 s


def test_a_flood_of_one_sender_costs_only_that_sender() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    admitted = {"cv0": 0, "cv9": 0}
    for k in range(10_000):  # cv9: 1,000 messages a second for 10 s; cv0: its 10 Hz
        t = k * 0.001
        admitted["cv9"] += a.admit("cv9", t) is None
        if k % 100 == 0:
            admitted["cv0"] += a.admit("cv0", t) is None
    assert admitted["cv0"] == 100
    assert admitted["cv9"] <= 20 + 20 * 10 + 1  # its burst and its rate, no more


def test_the_table_of_senders_is_bounded() -> None:
    a = Admission(rate_hz=10.0, max_senders=3)
    assert [a.admit(f"s{i}", 0.0) for i in range(5)] == [None, None, None, "too_many_senders", "too_many_senders"]
    assert len(a) == 3 and a.admit("s0", 1.0) is None  # the known ones go on


def test_a_clock_that_goes_back_gives_no_tokens() -> None:
    a = Admission(rate_hz=10.0, burst=1.0)
    assert a.admit("x", 100.0) is None
    assert a.admit("x", 0.0) == "flood"


@pytest.mark.parametrize(
    "kwargs", [{"rate_hz": 0.0}, {"rate_hz": 10.0, "burst": 0.5}, {"rate_hz": 1.0, "max_senders": 0}]
)
def test_bad_parameters_are_refused(kwargs) -> None:
    with pytest.raises(ValueError):
        Admission(**kwargs)


# ------------------------------------------------------------------------------ the gate: verify, then admit


def _signed_fleet():
    from mapcontainer.security import Signer, Verifier, issue, make_ca
    import msgpack

    from schemas.tags import TAGS

    now = 1.7e9
    ca = make_ca("ca", now=now - 60)
    signers = {v: Signer(issue(ca, v, 3600.0, now - 60)) for v in ("cv0", "cv1")}

    def prior(v: str, k: int) -> bytes:  # what the verifier reads of a payload: its sender (the rest is the host's)
        return msgpack.packb({TAGS["schema_version"]: 4, TAGS["sender"]: v, TAGS["seq"]: k})

    return now, Verifier(ca.certificate, 5.0), signers, prior


def test_a_flood_on_a_vehicles_key_costs_the_flooders_budget_not_the_vehicles() -> None:
    """The probe: 1,000 junk messages a second on cv1's key for 5 s. Junk fails verification and is charged
    to the key's unverified budget; cv1's genuine 10 Hz messages are verified and all admitted."""
    from mapcontainer.admission import Gate
    from mapcontainer.security import Verified

    now, verifier, signers, prior = _signed_fleet()
    gate = Gate(verifier, rate_hz=20.0, burst=20.0)
    admitted, junk_refused = {"cv0": 0, "cv1": 0}, 0
    for k in range(5000):
        t = k * 0.001
        out = gate.admit(b"\x93junk" + k.to_bytes(4, "big"), "cv1", t, now + t)
        junk_refused += not isinstance(out, Verified)
        if k % 100 == 0:
            for v in ("cv0", "cv1"):
                out = gate.admit(signers[v].sign(prior(v, k), now + t), v, t, now + t)
                assert isinstance(out, Verified) and out.sender == v, out
                admitted[v] += 1
    assert admitted == {"cv0": 50, "cv1": 50} and junk_refused == 5000
    assert gate.unverified_refused == 5000 and gate.verified.refused() == {}
    assert gate.unverified.refused()["cv1"] > 4000  # the flooder ran out of its own budget


def test_the_gate_admits_by_the_verified_sender() -> None:
    """A genuine vehicle's own flood is its verified budget's; an unsigned fleet's gate goes by the key."""
    from mapcontainer.admission import Gate
    from mapcontainer.security import Verified

    now, verifier, signers, prior = _signed_fleet()
    gate = Gate(verifier, rate_hz=10.0, burst=10.0)
    outs = [gate.admit(signers["cv0"].sign(prior("cv0", k), now), "cv0", 0.0, now) for k in range(12)]
    assert [isinstance(o, Verified) for o in outs] == [True] * 10 + [False] * 2
    assert outs[-1].reason == "flood" and gate.verified.refused() == {"cv0": 2}
    # a genuine message of cv1 on cv0's key: refused as a mismatch, charged to the key's unverified budget
    out = gate.admit(signers["cv1"].sign(prior("cv1", 0), now), "cv0", 0.0, now)
    assert out.reason == "sender_mismatch" and gate.unverified_refused == 1
    plain = Gate(None, rate_hz=10.0, burst=1.0)
    first = plain.admit(b"anything", "cv3", 0.0, now)
    assert isinstance(first, Verified) and (first.payload, first.sender) == (b"anything", "cv3")
    assert plain.admit(b"anything", "cv3", 0.0, now).reason == "flood"


def test_a_spent_unverified_budget_refuses_new_certificates_unchecked(monkeypatch) -> None:
    """While a source's unverified budget is spent, certificates not seen before cost no CA signature check
    (a stream of fresh fake certificates); known signers go on."""
    import mapcontainer.security as sec
    from mapcontainer.admission import Gate

    now, verifier, signers, prior = _signed_fleet()
    gate = Gate(verifier, rate_hz=10.0, burst=10.0, unverified_rate_hz=1.0)
    assert isinstance(gate.admit(signers["cv0"].sign(prior("cv0", 0), now), "cv0", 0.0, now), sec.Verified)
    assert gate.admit(b"junk", "cv1", 0.0, now).reason == "unsigned"  # cv1's one unverified token
    checks = []
    real = sec._valid
    monkeypatch.setattr(sec, "_valid", lambda *a: checks.append(1) or real(*a))
    out = gate.admit(signers["cv1"].sign(prior("cv1", 1), now), "cv1", 0.1, now)
    assert out.reason == "unknown_certificate" and checks == []
    assert isinstance(gate.admit(signers["cv0"].sign(prior("cv0", 2), now), "cv0", 0.1, now), sec.Verified)
    out = gate.admit(signers["cv1"].sign(prior("cv1", 3), now + 1.5), "cv1", 1.5, now + 1.5)  # a token back
    assert isinstance(out, sec.Verified), out
