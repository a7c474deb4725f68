"""Cost of signed V2X messages (``mapc bench security`` material): time per sign and per verify, bytes added.

The payload is a typical VehiclePrior (a pose, its covariance and ``objects`` detections). Every
figure is the median over ``iterations`` calls, wall clock, one call at a time. The yardstick of the
machine's speed at the time is the ``cryptography`` package alone signing and verifying the same
bytes (``ecdsa_*``), timed alternately with ours: ``sign_over_ecdsa`` and ``verify_over_ecdsa`` are the
medians of the paired ratios (digest signer), so what is above 1 is our own overhead.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from schemas import LocalizationQuality, ObjectObservations, VehiclePrior, encode

from .security import _ECDSA, Signer, Verifier, issue, make_ca

__all__ = ["bench_security", "typical_prior"]

T0 = 1.8e9  # Unix time of the synthetic run (2027)


def typical_prior(objects: int = 8, sender: str = "cv0", seed: int = 0) -> bytes:
    """An encoded VehiclePrior of ``sender`` with ``objects`` detections, as a vehicle sends ten times a second."""
    rng = np.random.default_rng(seed)
    p = rng.uniform([-40.0, -20.0, -0.5], [40.0, 20.0, 1.0], size=(objects, 3))
    cov = np.tile(np.diag([0.09, 0.04, 0.0025]), (objects, 1, 1))
    pose_cov = np.diag([0.04, 0.04, 0.01, 1e-4, 1e-4, 4e-4])
    prior = VehiclePrior(
        fleet="bench",
        sender=sender,
        seq=1234,
        t_meas=12.3,
        t_sent=12.35,
        pose=[105.2, -48.7, 0.3, 0.001, -0.002, 1.2],
        pose_cov=pose_cov[np.triu_indices(6)],
        v_map=[8.5, 2.1, 0.0],
        quality=LocalizationQuality(mode="map_matching", n_points=14, n_poles=6, n_lane=120, cost=0.8),
        objects=ObjectObservations.from_metres(p, cov, rng.integers(0, 4, objects)),
    )
    return encode(prior)


def _times_us(call: Callable[[int], object], i: int) -> float:
    t0 = time.perf_counter()
    call(i)
    return (time.perf_counter() - t0) * 1e6


def _p50_us(call: Callable[[int], object], n: int) -> float:
    """Median wall time (us) of ``call(i)`` for i in 0..n-1."""
    return float(np.median([_times_us(call, i) for i in range(n)]))


def _paired_us(ours: Callable[[int], object], raw: Callable[[int], object], n: int) -> tuple[float, float, float]:
    """Medians (us) of ``ours(i)`` and ``raw(i)`` called alternately, and the median of their ratios
    (paired: a load that comes and goes on the machine weighs on both alike)."""
    pairs = np.array([(_times_us(ours, i), _times_us(raw, i)) for i in range(n)])
    return float(np.median(pairs[:, 0])), float(np.median(pairs[:, 1])), float(np.median(pairs[:, 0] / pairs[:, 1]))


def bench_security(iterations: int = 1000, objects: int = 8) -> dict:
    """Sign and verify a typical VehiclePrior ``iterations`` times each way; returns the figures.

    ``verify_us_p50``: a message naming its signer by digest (the certificate known);
    ``verify_full_us_p50``: one carrying the full certificate, already verified before;
    ``verify_new_certificate_us_p50``: one carrying a certificate not seen yet (the CA's signature is
    checked and the key loaded too: what the first message of a vehicle costs).
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    payload = typical_prior(objects)
    ca = make_ca("bench-ca", now=T0 - 60)
    cv0, cv1 = (issue(ca, vid, 3600.0, T0 - 60) for vid in ("cv0", "cv1"))
    dt = 1e-3  # s between messages: all inside the window

    def times(k: int) -> list[float]:  # a block of generation times of its own per measurement
        return [T0 + k + i * dt for i in range(iterations)]

    digest_signer, full_signer = Signer(cv0, math.inf), Signer(cv0, 0.0)
    t_sign = times(1)
    digest_signer.sign(payload, t_sign[0] - dt)  # the first message carries the certificate
    key, pub = cv0.private_key, cv0.private_key.public_key()
    sign_us, ecdsa_sign_us, sign_ratio = _paired_us(
        lambda i: digest_signer.sign(payload, t_sign[i]), lambda i: key.sign(payload, _ECDSA), iterations
    )
    t_full = times(3)
    sign_full_us = _p50_us(lambda i: full_signer.sign(payload, t_full[i]), iterations)

    verifier = Verifier(ca.certificate, window_s=1.0)
    first = Signer(cv0, math.inf)
    verifier.verify(first.sign(payload, T0 + 4.5), T0 + 4.5)  # learns cv0's certificate
    t_v = times(5)
    signed = [first.sign(payload, t) for t in t_v]
    der = key.sign(payload, _ECDSA)
    verify_us, ecdsa_verify_us, verify_ratio = _paired_us(
        lambda i: verifier.verify(signed[i], t_v[i], "cv0"), lambda i: pub.verify(der, payload, _ECDSA), iterations
    )
    t_vf = times(7)
    signed_full = [full_signer.sign(payload, t) for t in t_vf]
    verify_full_us = _p50_us(lambda i: verifier.verify(signed_full[i], t_vf[i], "cv0"), iterations)

    # two vehicles alternating through a cache of one certificate: every message brings a new one
    fresh = Verifier(ca.certificate, window_s=1.0, max_certificates=1)
    p1 = typical_prior(objects, "cv1")
    signers = (Signer(cv0, 0.0), Signer(cv1, 0.0))
    t_n = times(9)
    signed_new = [signers[i % 2].sign(payload if i % 2 == 0 else p1, t) for i, t in enumerate(t_n)]
    verify_new_us = _p50_us(lambda i: fresh.verify(signed_new[i], t_n[i]), iterations)
    refused = verifier.rejected + fresh.rejected
    if refused:
        raise RuntimeError(f"the bench's own messages were refused: {dict(refused)}")

    return {
        "iterations": iterations,
        "objects": objects,
        "prior_bytes": len(payload),
        "bytes_added_digest": len(signed[0]) - len(payload),
        "bytes_added_full": len(signed_full[0]) - len(payload),
        "sign_us_p50": round(sign_us, 1),
        "sign_full_us_p50": round(sign_full_us, 1),
        "verify_us_p50": round(verify_us, 1),
        "verify_full_us_p50": round(verify_full_us, 1),
        "verify_new_certificate_us_p50": round(verify_new_us, 1),
        "ecdsa_sign_us_p50": round(ecdsa_sign_us, 1),
        "ecdsa_verify_us_p50": round(ecdsa_verify_us, 1),
        "sign_over_ecdsa": round(sign_ratio, 2),
        "verify_over_ecdsa": round(verify_ratio, 2),
    }


if __name__ == "__main__":  # python -m mapcontainer.security_bench
    import json

    print(json.dumps(bench_security(), indent=2))
