"""The host's batched rewrites give the numbers of the per-object code they replaced (seeded scenes).

Each reference below is the per-object code as it was before it was batched, kept here as the oracle.
"""

from __future__ import annotations

import numpy as np

from mapcontainer import geometry as geo
from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.hostcore import observer_bias, observer_biases
from mapcontainer.fusion.mapframe import rotated_to_map
from mapcontainer.fusion.misbehaviour import MisbehaviourMonitor


def _observer_bias_per_object(p_map, observers: list[tuple]) -> np.ndarray:
    """hostcore.observer_bias before it was batched: one map projection per observer and object."""
    p = np.asarray(p_map, dtype=float)
    C = np.zeros((3, 3))
    for pose, S_v, w, *rest in observers:
        pose = np.asarray(pose, dtype=float)
        jac = geo.rpy_to_matrix_jac(*pose[3:6])
        z = jac[0].T @ (p - pose[:3])
        D = rest[0] if rest and rest[0] is not None else np.zeros((3, 3))
        C += w * w * rotated_to_map(pose, jac, S_v, z[None], np.asarray(D, dtype=float)[None])[1][0]
    return C


def _spd(rng, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + 1e-6 * np.eye(n)


def test_observer_biases_of_many_objects_are_the_per_object_numbers() -> None:
    """Seeded scene: 12 observers, 200 objects, each seen by 0-5 observers in a random order with random
    shares, some with a persistent detection error D and some without; every object's term equals the
    per-object code's to the last bit, and observer_bias (one object) too."""
    rng = np.random.default_rng(3601)
    observers = {
        f"cv{i}": (
            np.concatenate([rng.uniform(-200, 200, 3) * [1, 1, 0], rng.normal(0, 0.05, 2), [rng.uniform(-3, 3)]]),
            _spd(rng, 6, 0.05),
        )
        for i in range(12)
    }
    names = list(observers)
    p = rng.uniform(-250, 250, (200, 3))
    seen = []
    for _ in range(len(p)):
        who = rng.permutation(names)[: rng.integers(0, 6)]
        w = rng.dirichlet(np.ones(len(who))) if len(who) else []
        D = [_spd(rng, 3, 0.1) if rng.random() < 0.7 else None for _ in who]
        seen.append([(o, float(wo), d) for o, wo, d in zip(who, w, D, strict=True)])
    got = observer_biases(p, seen, observers)
    for k in range(len(p)):
        ref = _observer_bias_per_object(p[k], [(*observers[o], w, D) for o, w, D in seen[k]])
        assert np.array_equal(got[k], ref), (k, got[k] - ref)
        assert np.array_equal(observer_bias(p[k], [(*observers[o], w, D) for o, w, D in seen[k]]), ref)
    assert observer_biases(np.zeros((0, 3)), [], observers).shape == (0, 3, 3)


class _EveryReportEveryUpdate(MisbehaviourMonitor):
    """The monitor before its report test was cached: every sighting tested against every report present,
    one sighting at a time, at every update (its ``matched``: the newest present report that matched)."""

    def _reported_there(self, sightings) -> None:
        for vid, q in sightings.items():
            for s in q:
                s.matched = -1
                for t, p, S, no in self._reports.get(vid, ()):
                    if abs(t - s.t) > 0.05:
                        continue
                    d = p - s.where
                    C = S + s.det_cov
                    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(C, d[..., None])[..., 0])
                    if (d2 <= self._gate).any():
                        s.matched = no


def _counted(mon: MisbehaviourMonitor) -> list[tuple]:
    """Every sighting in the window and whether it counts (the observed vehicle did not report an object there)."""
    out = []
    for vid, q in mon._sightings.items():
        reports = mon._reports.get(vid)
        front = reports[0][3] if reports else mon._report_no
        out += [(vid, s.t, s.observer, s.matched < front) for s in q]
    return out


def test_the_cached_report_test_decides_what_the_test_of_every_report_at_every_update_did() -> None:
    """Seeded scene: 6 vehicles 10 m apart, parked cars beside some of them (which they report and others
    see), clocks up to 40 ms apart (a report can leave the window before the sighting at its instant),
    late and lost messages, one vehicle 3 m off from 4 s on. After every update, the same sightings count,
    and the same pairs are disputed and vehicles flagged, as when every report is tested anew."""
    rng = np.random.default_rng(3602)
    params = FusionParams()
    new, ref = MisbehaviourMonitor(params), _EveryReportEveryUpdate(params)
    vids = [f"cv{i}" for i in range(6)]
    truth = np.array([[10.0 * i, 0.0, 0.0] for i in range(6)])
    parked = np.array([[10.0 * i + 2.5, 3.0, 0.0] for i in (1, 3, 4)])
    clock = rng.uniform(-0.04, 0.04, len(vids))
    late: list[tuple] = []
    flagged_any = False
    for k in range(80):
        t = 0.1 * k
        said = truth + np.where(np.arange(6)[:, None] == 2, [3.0, 0.0, 0.0] if t >= 4.0 else 0.0, 0.0)
        reported = (np.array(vids), said, np.tile(0.04 * np.eye(3), (6, 1, 1)))
        calls = late
        late = []
        for i, o in enumerate(vids):
            if rng.random() < 0.1:
                continue  # lost
            things = np.vstack([np.delete(truth, i, axis=0), parked])
            things = things[np.linalg.norm(things - truth[i], axis=1) < 30.0]
            p = things + rng.normal(0.0, 0.2, things.shape) + (said[i] - truth[i])
            cov = np.tile(np.diag([0.09, 0.09, 0.01]), (len(p), 1, 1)) * rng.uniform(0.5, 2.0, (len(p), 1, 1))
            cls = rng.choice([0, 2, 2, 1], len(p))
            call = (o, t + clock[i], p, cov, cls, reported)
            (late if rng.random() < 0.15 else calls).append(call)
        for call in calls:
            new.observe(*call)
            ref.observe(*call)
        assert new.update(t) == ref.update(t)
        assert new.disputed == ref.disputed
        assert _counted(new) == _counted(ref)
        assert new.views.keys() == ref.views.keys()
        for key, (m, C) in new.views.items():
            assert np.array_equal(m, ref.views[key][0]) and np.array_equal(C, ref.views[key][1]), key
        flagged_any |= bool(new.flagged)
    assert flagged_any  # the biased cv2 was flagged: the scene exercises the decisions


def test_the_benchs_cpu_phases_leave_out_waits_and_change_no_figure() -> None:
    """``cpu_clock``: a Laps made inside charges CPU time (a sleep costs none), the clock is wall again after;
    ``bench_fusion(cpu_phases=True)`` says so and gives the same accuracy figures as the wall-clock run."""
    import time

    from mapcontainer.fusion.bench import bench_fusion
    from mapcontainer.fusion.laps import Laps, cpu_clock

    with cpu_clock():
        laps = Laps()
        time.sleep(0.2)
        laps.mark("slept")
    assert laps.ms["slept"] < 100.0
    wall = Laps()
    time.sleep(0.05)
    wall.mark("slept")
    assert wall.ms["slept"] >= 50.0 and Laps.clock is time.perf_counter
    cpu, plain = bench_fusion(3, 6, 3, ticks=8, cpu_phases=True), bench_fusion(3, 6, 3, ticks=8)
    assert (cpu["phases_clock"], plain["phases_clock"]) == ("cpu", "wall")
    assert cpu["phases_ms_p50"].keys() == plain["phases_ms_p50"].keys()
    for key in ("object_rmse_m", "object_anees", "vehicle_rmse_m", "object_matches"):
        assert cpu[key] == plain[key]
