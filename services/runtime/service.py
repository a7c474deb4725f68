"""The Service runtime: session, liveliness token, health, subscribers and publishers, signals."""

from __future__ import annotations

import faulthandler
import logging
import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapcontainer import jsonout
from mapcontainer.admission import Gate
from mapcontainer.security import CredentialsMissing, Signer, Verifier, service_signer
from schemas import HealthStatus, decode, encode
from schemas.topics import max_bytes, topic

from .clock import read_attachment
from .config import ServiceSettings, ZenohSettings, open_session
from .metrics import DEGRADED_AFTER_REJECT_S, DEGRADING_REJECTS, STATES, ServiceMetrics, build_health

EXIT_THREAD_DIED = 70  # EX_SOFTWARE: a service whose worker thread died exits with it
# Undeclaring and closing the Zenoh session are given this long; then the process exits anyway, with the
# stacks of its threads in its log. A close that never returns is a known, rare Zenoh defect
# (eclipse-zenoh/zenoh#969); a service asked to stop must stop.
CLOSE_DEADLINE_S = 5.0


# ------------------------------------------------------------------------------ the service


@dataclass(frozen=True)
class Received:
    """A sample handed to a queued handler: payload bytes, key, attachment and wall time of arrival."""

    key: str
    payload: bytes
    attachment: dict[str, Any]
    t_recv_wall_ns: int


class CountingPublisher:
    """A Zenoh publisher whose puts are counted as messages/bytes out."""

    def __init__(self, pub, metrics: ServiceMetrics):
        self._pub = pub
        self._metrics = metrics
        self.key = str(pub.key_expr)

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self._pub.put(payload, attachment=attachment)
        self._metrics.msgs_out.add(len(payload))

    @property
    def matching(self) -> bool:
        return bool(self._pub.matching_status.matching)

    def undeclare(self) -> None:
        self._pub.undeclare()


def topic_gate(topic_name: str, verifier: Verifier | None, time_scale: float = 1.0, max_senders: int = 256) -> Gate:
    """:class:`~mapcontainer.admission.Gate` for a topic: each verified sender (the key's sender on an
    unsigned fleet), and each source of traffic that fails verification, may send twice the topic's nominal
    rate in wall time (``time_scale`` scenario seconds per wall second), one second of that as a burst."""
    rate = 2.0 * (topic(topic_name).rate_hz or 10.0) * max(time_scale, 1.0)
    return Gate(verifier, rate, rate, max_senders)


class Service:
    """A service process's runtime: session, liveliness token, health, counters, signals.

    Use as a context manager in the main thread. ``figures`` (a callable returning the core's
    stats dict) and ``health_check`` (returning ``(state, note)``) refine the health status. With
    ``keys`` (the fleet's keys directory), the health status is signed with the service's own credentials
    (its id's), so that ``mapc health`` believes only what the service said.
    Worker threads started with :meth:`spawn` are joined before the session closes. A worker thread
    that dies of an exception turns the health to failed and stops the service, which then exits
    with :data:`EXIT_THREAD_DIED` so that the launcher restarts it as it restarts a crashed one (a
    process alive but dead inside would never be restarted).
    """

    def __init__(
        self,
        role: str,
        settings: ServiceSettings,
        figures: Callable[[], Mapping[str, Any]] | None = None,
        health_check: Callable[[], tuple[str, str | None]] | None = None,
        session_opener: Callable[[ZenohSettings], Any] = open_session,
        keys: str | Path | None = None,
    ):
        self.role = role
        self.settings = settings
        self.fleet = settings.fleet
        self.id = settings.id
        self.log = logging.getLogger(f"mapc.{role}")
        self.metrics = ServiceMetrics(settings.rate_window_s)
        self.figures = figures
        self.health_check = health_check
        self.running = threading.Event()
        self.stop_requested = threading.Event()
        self.session = None
        self._opener = session_opener
        self._t0 = time.monotonic()
        self._health_seq = 0
        self._state: str = "ok"
        self._state_note: str | None = None
        self._threads: list[threading.Thread] = []
        self.thread_died: str | None = None  # the first worker thread that died, and why
        self._declared: list[Any] = []
        self._worlds: set[str] | None = None  # the fleet's world tokens alive (None: not watched)
        self._old_handlers: dict[int, Any] = {}
        self._parent = os.getppid()
        self.health_key = topic("health").key(fleet=self.fleet, role=role, id=self.id)
        self._health_signer: Signer | None = None
        self._sign_lock = threading.Lock()  # the health loop and the queryable's thread both sign
        if keys is not None:
            try:
                self._health_signer = service_signer(keys, self.id)
            except CredentialsMissing as e:  # keys made before services signed: health goes unsigned
                self.log.warning("health is not signed: %s", e)
        self.alive_key = topic("alive").key(fleet=self.fleet, role=role, id=self.id)

    # -- lifecycle ------------------------------------------------------------------------
    def __enter__(self) -> Service:
        self._install_signals()
        self.session = self._opener(self.settings.zenoh)
        try:
            import zenoh

            self._health_pub = self.session.declare_publisher(
                self.health_key, congestion_control=zenoh.CongestionControl.DROP
            )
            self._queryable = self.session.declare_queryable(self.health_key, self._on_health_query)
            self._token = None
            if self.settings.stale_input_s is not None:  # whether stalled input means the run ended
                self._worlds = self.watch_tokens(topic("alive").pattern(fleet=self.fleet, role="world"))
            self.running.set()
            self.spawn(self._health_loop, name="health")
        except BaseException:
            self.session.close()
            raise
        self.log.info(
            "up: %s (zenoh %s, connect %s)",
            self.alive_key,
            self.settings.zenoh.mode,
            self.settings.zenoh.connect,
        )
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None and not isinstance(exc, KeyboardInterrupt):
            self.metrics.error(f"{type(exc).__name__}: {exc}")
            self.log.error("stopping after an error: %s", exc, exc_info=(exc_type, exc, tb))
        self.stop()
        self.running.clear()
        for th in self._threads:
            if th is not threading.current_thread():
                th.join(timeout=5.0)
                if th.is_alive():
                    self.log.warning("thread %s did not stop within 5 s", th.name)
        code = EXIT_THREAD_DIED if self.thread_died is not None and exc is None else 0 if exc is None else 1
        watchdog = threading.Timer(CLOSE_DEADLINE_S, self._close_hung, args=(code,))
        watchdog.daemon = True
        watchdog.start()
        try:
            for d in reversed(self._declared):
                try:
                    d.undeclare()
                except Exception as e:  # already undeclared or session gone: nothing to do
                    self.log.debug("undeclare: %s", e)
            if self._token is not None:
                self._token.undeclare()
            self._queryable.undeclare()
            self._health_pub.undeclare()
        finally:
            self.session.close()
            watchdog.cancel()
            self._restore_signals()
            self.log.info("stopped after %.1f s", time.monotonic() - self._t0)
        if self.thread_died is not None and exc is None:
            raise SystemExit(EXIT_THREAD_DIED)

    def _close_hung(self, code: int) -> None:
        self.log.error(
            "closing the Zenoh session did not finish within %.0f s: exiting %d without it; thread stacks follow",
            CLOSE_DEADLINE_S,
            code,
        )
        for h in logging.getLogger().handlers:
            h.flush()
        faulthandler.dump_traceback(all_threads=True)
        os._exit(code)

    def ready(self) -> None:
        """Declare the liveliness token: the service is wired (subscribers declared) and working.

        The launcher starts the next group when it sees the token, so roles call this after their
        subscribers exist; :meth:`wait` calls it if the role did not.
        """
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.alive_key)
            self.log.info("ready: %s", self.alive_key)

    def stop(self) -> None:
        """Ask the service to stop (safe from any thread or a signal handler)."""
        self.stop_requested.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until stop is requested (True) or ``timeout`` passes (False). Signal-friendly."""
        self.ready()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop_requested.is_set():
            left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
            if left <= 0:
                return False
            self.stop_requested.wait(left)
        return True

    @property
    def uptime_s(self) -> float:
        return time.monotonic() - self._t0

    def _install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old_handlers[sig] = signal.signal(sig, self._on_signal)
        faulthandler.register(signal.SIGUSR1, all_threads=True)  # `kill -USR1 PID`: the stacks of a stuck service

    def _restore_signals(self) -> None:
        if self._old_handlers:
            faulthandler.unregister(signal.SIGUSR1)
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        self._old_handlers.clear()

    def _on_signal(self, signum, frame) -> None:
        self.log.info("signal %s: stopping", signal.Signals(signum).name)
        self.stop()

    def spawn(self, target: Callable[[], None], name: str) -> threading.Thread:
        """Start a daemon thread that should return once ``stop_requested`` is set."""

        def run():
            try:
                target()
            except Exception as e:
                self.metrics.error(f"{name}: {type(e).__name__}: {e}")
                self.set_state("failed", f"thread {name} died: {type(e).__name__}: {e}")
                self.log.exception("thread %s died: the service stops and exits %d", name, EXIT_THREAD_DIED)
                self.thread_died = self.thread_died or f"{name}: {type(e).__name__}: {e}"
                self.stop()

        th = threading.Thread(target=run, name=f"{self.role}-{name}", daemon=True)
        self._threads.append(th)
        th.start()
        return th

    # -- state and health -------------------------------------------------------------------
    def set_state(self, state: str, note: str | None = None) -> None:
        if state not in STATES:
            raise ValueError(f"state must be one of {STATES}, got {state!r}")
        self._state, self._state_note = state, note

    def current_state(self) -> tuple[str, str | None]:
        """The worst of: the state set explicitly, the role's check, stalled input, recent errors."""
        candidates: list[tuple[str, str | None]] = [(self._state, self._state_note)]
        if self.health_check is not None:
            try:
                candidates.append(self.health_check())
            except Exception as e:
                candidates.append(("degraded", f"health check raised {type(e).__name__}: {e}"))
        idle = self.metrics.msgs_in.idle_s()
        stale = self.settings.stale_input_s
        if stale is not None and idle is not None and idle > stale:
            if self._worlds is not None and not self._worlds:
                # no world alive: it finished (or this is a replay fleet, whose replay ended)
                candidates.append(("finished", f"input ended {idle:.0f} s ago; no world runs (finished or replayed)"))
            else:
                candidates.append(("degraded", f"input stalled for {idle:.1f} s"))
        if self.metrics.last_error_t is not None and time.monotonic() - self.metrics.last_error_t < 10.0:
            candidates.append(("degraded", self.metrics.last_error))
        for reason, (n, detail) in self.metrics.recent_rejects(DEGRADING_REJECTS, DEGRADED_AFTER_REJECT_S).items():
            candidates.append(("degraded", f"input lost: {reason} ({n} so far; the last: {detail})"))
        return max(candidates, key=lambda c: STATES.index(c[0]))

    def health(self) -> HealthStatus:
        state, note = self.current_state()
        figures: Mapping[str, Any] = {}
        if self.figures is not None:
            try:
                figures = self.figures()
            except Exception as e:
                self.metrics.error(f"figures: {type(e).__name__}: {e}")
        self._health_seq += 1
        return build_health(
            fleet=self.fleet,
            role=self.role,
            sid=self.id,
            seq=self._health_seq,
            uptime_s=self.uptime_s,
            metrics=self.metrics,
            state=state,
            note=note if state != "ok" else None,
            figures=figures,
        )

    def health_payload(self) -> bytes:
        """The health status as it goes on the bus: encoded, and signed where the service has credentials."""
        data = encode(self.health())
        if self._health_signer is None:
            return data
        with self._sign_lock:
            return self._health_signer.sign(data, time.time())

    def _on_health_query(self, query) -> None:
        try:
            query.reply(self.health_key, self.health_payload())
        except Exception as e:  # a failed reply must not kill the Zenoh callback thread
            self.log.warning("health reply failed: %s", e)

    def _health_loop(self) -> None:
        next_t = time.monotonic()
        while not self.stop_requested.is_set():
            if self.settings.watch_parent and os.getppid() != self._parent:
                self.log.warning("parent process %d is gone: stopping", self._parent)
                self.stop()
                break
            now = time.monotonic()
            if now >= next_t:
                try:
                    self._health_pub.put(self.health_payload())
                except Exception as e:
                    self.log.warning("health put failed: %s", e)
                next_t = now + self.settings.health_period_s
            self.stop_requested.wait(min(0.25, max(next_t - time.monotonic(), 0.01)))

    # -- pub/sub helpers --------------------------------------------------------------------
    def publisher(self, key: str, drop: bool = False, express: bool = False) -> CountingPublisher:
        """A counted publisher; ``drop=True`` for telemetry where newest wins (CongestionControl.DROP)."""
        import zenoh

        cc = zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK
        pub = self.session.declare_publisher(key, congestion_control=cc, express=express)
        self._declared.append(pub)
        return CountingPublisher(pub, self.metrics)

    def subscribe(self, key: str, callback: Callable[[Received], None], count: bool = True):
        """A callback subscriber (runs on a Zenoh thread: keep ``callback`` short).

        Input is counted; an exception in ``callback`` is recorded as the last error, never raised
        into Zenoh. A payload over its topic's size bound (:func:`schemas.topics.max_bytes`) is refused
        as ``too_large`` before its bytes are copied out of Zenoh.
        """
        bound = max_bytes(key)

        def on_sample(sample) -> None:
            if not self._fits(sample, bound):
                return
            payload = sample.payload.to_bytes()
            if count:
                self.metrics.msgs_in.add(len(payload))
            try:
                callback(Received(str(sample.key_expr), payload, read_attachment(sample), time.time_ns()))
            except Exception as e:
                self.metrics.error(f"{type(e).__name__}: {e}")
                self.log.exception("subscriber callback on %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._declared.append(sub)
        return sub

    def _fits(self, sample, bound: int) -> bool:
        """Whether ``sample``'s payload is within ``bound`` bytes (its length, read without copying it)."""
        n = len(sample.payload)
        if n <= bound:
            return True
        self.metrics.msgs_in.add(0)  # an arrival, not bytes we read
        self.metrics.reject("too_large", f"{n} bytes on {sample.key_expr} (at most {bound})", self.log)
        return False

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes, bytes | None, int], None]):
        """A callback subscriber handed ``(key, payload, attachment bytes or None, receive wall ns)``: the
        bytes as they travelled (the recorder keeps them). Input is counted; exceptions and sizes as in
        :meth:`subscribe`."""
        bound = max_bytes(key)

        def on_sample(sample) -> None:
            if not self._fits(sample, bound):
                return
            payload = sample.payload.to_bytes()
            self.metrics.msgs_in.add(len(payload))
            att = sample.attachment
            try:
                callback(str(sample.key_expr), payload, None if att is None else att.to_bytes(), time.time_ns())
            except Exception as e:
                self.metrics.error(f"{type(e).__name__}: {e}")
                self.log.exception("subscriber callback on %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._declared.append(sub)
        return sub

    def watch_tokens(self, pattern: str) -> set[str]:
        """The keys of the liveliness tokens matching ``pattern`` that exist, kept current (a set that
        Zenoh's callbacks update; reading its emptiness needs no lock)."""
        import zenoh

        keys: set[str] = set()

        def on_token(sample) -> None:
            (keys.add if sample.kind == zenoh.SampleKind.PUT else keys.discard)(str(sample.key_expr))

        self._declared.append(self.session.liveliness().declare_subscriber(pattern, on_token, history=True))
        return keys

    def watch_alive(self, key: str) -> threading.Event:
        """An event that is set while the liveliness token ``key`` exists (Zenoh tells of a killed process
        within milliseconds, of a frozen one after its lease)."""
        import zenoh

        alive = threading.Event()

        def on_token(sample) -> None:
            (alive.set if sample.kind == zenoh.SampleKind.PUT else alive.clear)()

        self._declared.append(self.session.liveliness().declare_subscriber(key, on_token, history=True))
        return alive

    def subscribe_queued(
        self,
        key: str,
        handler: Callable[[Received], None],
        maxsize: int = 16,
        name: str = "worker",
    ):
        """Subscribe with a bounded queue and one worker thread running ``handler`` in arrival order.

        When ``maxsize`` samples wait for ``handler``, a new sample is counted as reject ``queue_full``
        and dropped. The handler's run time is recorded as the processing latency. (A vehicle's frames
        use a backlog whose newest frame wins instead: ``mapcontainer.vehicle.FrameBacklog``.)
        """
        q: queue.SimpleQueue[Received] = queue.SimpleQueue()
        lock = threading.Lock()
        waiting = 0  # samples in q

        def enqueue(msg: Received) -> None:
            nonlocal waiting
            with lock:
                full = waiting >= maxsize
                waiting += not full
            if full:
                self.metrics.reject("queue_full", f"{name}: {maxsize} samples waiting, dropped", self.log)
                return
            q.put(msg)

        def work() -> None:
            nonlocal waiting
            while not self.stop_requested.is_set():
                try:
                    msg = q.get(timeout=0.2)
                except queue.Empty:
                    continue
                with lock:
                    waiting -= 1
                t0 = time.perf_counter()
                try:
                    handler(msg)
                except Exception as e:
                    self.metrics.error(f"{type(e).__name__}: {e}")
                    self.log.exception("handler %s failed on %s", name, msg.key)
                self.metrics.latency.add(time.perf_counter() - t0)

        self.spawn(work, name)
        return self.subscribe(key, enqueue)

    def decode_or_reject(self, payload: bytes, model):
        """``schemas.decode``; a Rejection is counted by reason and None returned."""
        msg = decode(payload, model)
        if not msg:
            self.metrics.reject(msg.reason, msg.detail, self.log)
            return None
        return msg

    def wait_matching(self, pubs: Iterable[CountingPublisher], timeout_s: float) -> bool:
        """Wait until every publisher has a matching subscriber (or the timeout, or stop)."""
        pubs = list(pubs)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.stop_requested.is_set():
            if all(p.matching for p in pubs):
                return True
            self.stop_requested.wait(0.05)
        return all(p.matching for p in pubs)


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (write to a temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(jsonout.dumps(data, indent=2, default=str))
    os.replace(tmp, path)
