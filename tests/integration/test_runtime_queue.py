"""``Service`` on a real Zenoh session: ``subscribe_queued`` (order, bound), worker threads."""

from __future__ import annotations

import threading

import pytest

from services.runtime import EXIT_THREAD_DIED, Service, ServiceSettings, ZenohSettings


def test_a_full_queue_drops_new_samples(fleet_name, wait_for) -> None:
    settings = ServiceSettings(fleet=fleet_name, id="q0", zenoh=ZenohSettings(listen=["tcp/127.0.0.1:0"]))
    calls: list[bytes] = []
    started, release = threading.Event(), threading.Event()

    def handler(msg) -> None:
        calls.append(msg.payload)
        started.set()
        release.wait(10.0)

    with Service("vehicle", settings) as svc:
        key = f"{fleet_name}/test/frames"
        svc.subscribe_queued(key, handler, maxsize=2, name="frames")
        pub = svc.publisher(key)
        pub.put(b"0")
        assert started.wait(10.0), "the worker never took the first sample"
        for k in range(1, 6):  # the worker is busy with "0": "1" and "2" wait, "3"-"5" find the queue full
            pub.put(str(k).encode())
        wait_for(lambda: svc.metrics.rejects.get("queue_full") == 3, 10.0, "3 samples over the bound")
        assert svc.current_state()[0] == "degraded"  # lost input degrades
        release.set()
        wait_for(lambda: len(calls) == 3, 10.0, "every sample queued handled")
    assert calls == [b"0", b"1", b"2"]
    assert svc.metrics.latency.percentiles_ms()[0] is not None  # the handler's run time is recorded


def test_a_worker_thread_that_dies_fails_the_service_and_ends_it_with_exit_70(fleet_name) -> None:
    """A process alive but dead inside is never restarted: the service stops and exits EX_SOFTWARE."""
    settings = ServiceSettings(fleet=fleet_name, id="t0", zenoh=ZenohSettings(listen=["tcp/127.0.0.1:0"]))

    def broken() -> None:
        raise OverflowError("a clock from an attachment")

    with pytest.raises(SystemExit) as exit_info:
        with Service("host", settings) as svc:
            svc.spawn(broken, "fusion")
            assert svc.wait(timeout=10.0), "the dead thread did not stop the service"
            state, note = svc.current_state()
            assert state == "failed" and "fusion" in note and "OverflowError" in note
    assert exit_info.value.code == EXIT_THREAD_DIED == 70
    assert svc.metrics.errors == 1 and "fusion: OverflowError" in svc.thread_died
