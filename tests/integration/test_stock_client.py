"""Acceptance: a stock Zenoh client that knows only the endpoint from ``mapc fleet status --json`` and
schemas/README.md subscribes to the fused output and decodes it with plain msgpack + numpy.

Nothing from ``schemas`` or ``services`` is used on the client side: the key expression, the session
configuration and the decoder are written out here as a reader of the README would.
"""

from __future__ import annotations

import json
import queue
from pathlib import Path

import msgpack
import numpy as np
import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def decode_fused_state(data: bytes) -> dict:
    """schemas/README.md, "Decoding without our code", verbatim."""
    msg = msgpack.unpackb(data, raw=False)
    if msg.get("schema_version") != 1:
        raise ValueError(f"unsupported schema_version {msg.get('schema_version')!r}")

    def arr(name, dtype, cols=None):  # msgpack bin -> little-endian, row-major array
        a = np.frombuffer(msg.get(name, b""), dtype=np.dtype(dtype).newbyteorder("<"))
        return a if cols is None else a.reshape(-1, cols)

    def full_cov(upper, n):  # row-major upper triangle -> symmetric (N, n, n)
        iu = np.triu_indices(n)
        cov = np.zeros((len(upper), n, n))
        cov[:, iu[0], iu[1]] = upper
        cov[:, iu[1], iu[0]] = upper
        return cov

    return {
        "t_meas": msg["t_meas"],
        "vehicle_ids": msg.get("vehicle_ids", []),
        "vehicle_pose": arr("vehicle_pose", "f4", 6),
        "vehicle_pose_cov": full_cov(arr("vehicle_pose_cov", "f4", 21), 6),
        "object_id": arr("object_id", "u4"),
        "object_cls": arr("object_cls", "u1"),
        "object_p_map": arr("object_p_map", "f4", 3),
        "object_v_map": arr("object_v_map", "f4", 3),
        "object_cov": full_cov(arr("object_cov", "f4", 6), 3),
    }


def test_stock_zenoh_client_subscribes_to_fused_and_decodes_with_plain_msgpack(tmp_path, fleet_name, mapc):
    import zenoh

    runs = tmp_path / "runs"
    up = mapc(
        "fleet", "up", "--detach", "--json", "--fleet", fleet_name, "--vehicles", "2", "--network", "ideal",
        "--runs-dir", str(runs),
        timeout=240,
    )  # fmt: skip
    assert up.returncode == 0, up.stdout + up.stderr
    pgid_run_dir = Path(json.loads(up.stdout)["run_dir"])
    try:
        st = mapc("fleet", "status", "--json", "--fleet", fleet_name, "--runs-dir", str(runs))
        assert st.returncode == 0, st.stdout + st.stderr
        endpoint = next(e for e in json.loads(st.stdout)[0]["endpoints"] if "127.0.0.1" in e)

        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("client"))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        got: queue.Queue = queue.Queue()
        with zenoh.open(conf) as session:
            sub = session.declare_subscriber(
                f"mc/{fleet_name}/host/*/fused", lambda s: got.put((str(s.key_expr), s.payload.to_bytes()))
            )
            try:
                key, payload = got.get(timeout=60)
            finally:
                sub.undeclare()
        assert key.startswith(f"mc/{fleet_name}/host/") and key.endswith("/fused")
        fused = decode_fused_state(payload)
        v = len(fused["vehicle_ids"])
        assert v >= 1 and fused["vehicle_pose"].shape == (v, 6)
        assert fused["vehicle_pose_cov"].shape == (v, 6, 6)
        assert np.all(np.isfinite(fused["vehicle_pose"])) and fused["t_meas"] >= 0
        n = len(fused["object_id"])
        assert fused["object_p_map"].shape == (n, 3) and fused["object_cov"].shape == (n, 3, 3)
        assert fused["object_cls"].shape == (n,)
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, "--runs-dir", str(runs), timeout=180)
    assert down.returncode == 0, down.stdout + down.stderr
    assert (pgid_run_dir / "report.json").exists()
