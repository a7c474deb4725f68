"""Acceptance: a stock Zenoh client that knows only the endpoint from ``mapc fleet status --json`` and
schemas/README.md subscribes to the fused output and decodes it with plain msgpack + numpy.

Nothing from ``schemas`` or ``services`` is used on the client side: the key expression, the session
configuration and the decoder are written out here as a reader of the README would.
"""

from __future__ import annotations

import json
import queue
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]


README = Path(__file__).resolve().parents[2] / "schemas" / "README.md"


def readme_decoder():
    """The ``decode_fused_state`` recipe exactly as schemas/README.md prints it, run as a reader would."""
    text = README.read_text(encoding="utf-8")
    blocks = text.split("```python")[1:]
    code = next(b.split("```")[0] for b in blocks if "def decode_fused_state" in b)
    namespace: dict = {}
    exec(code, namespace)  # noqa: S102 - the README's own code
    return namespace["decode_fused_state"]


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
        st = mapc("fleet", "status", "--json", "--fleet", fleet_name)
        assert st.returncode == 0, st.stdout + st.stderr
        endpoint = next(e for e in json.loads(st.stdout)[0]["endpoints"] if "127.0.0.1" in e)

        # the fleet's mesh asks for a login: the operator's, a Zenoh configuration file in the run directory
        conf = zenoh.Config.from_file(str(pgid_run_dir / "zenoh" / "ops.json5"))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
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
        import msgpack

        # a signed fleet wraps its fused state in a SecuredMessage: the message is its tag 89 (schemas/README.md;
        # open_signed there checks the signatures too)
        fused = readme_decoder()(msgpack.unpackb(payload, strict_map_key=False)[89])
        v = len(fused["vehicle_ids"])
        assert v >= 1 and fused["vehicle_pose"].shape == (v, 6)
        assert fused["vehicle_pose_cov"].shape == (v, 6, 6)
        assert np.all(np.isfinite(fused["vehicle_pose"])) and fused["t_meas"] >= 0
        n = len(fused["object_id"])
        assert fused["object_p_map"].shape == (n, 3) and fused["object_cov"].shape == (n, 3, 3)
        assert fused["object_cls"].shape == (n,)
    finally:
        down = mapc("fleet", "down", "--fleet", fleet_name, timeout=180)
    assert down.returncode == 0, down.stdout + down.stderr
    assert (pgid_run_dir / "report.json").exists()
