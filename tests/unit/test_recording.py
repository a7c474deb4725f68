"""Recordings: the MCAP layout (exact payloads, attachments, times), Foxglove channels, the size bound,
files cut short, replay's byte rewrites, and re-fusion reproducing the host's fused states."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from mapcontainer.host import HostSetup
from mapcontainer.recording import RecordingError, RecordingWriter, info, read_records
from mapcontainer.recording.foxglove import SCENE_UPDATE, ellipsoid, map_scene, visualizer
from mapcontainer.recording.replay import refuse, replay_plan, retarget, shift_attachment, shift_clock
from mapcontainer.security import Signer, issue, make_ca
from schemas import FusedState, GroundTruth, decode, encode
from schemas.codec import peek
from schemas.models import SecuredMessage, VehiclePrior
from schemas.topics import topic

REPO = Path(__file__).resolve().parents[2]


def truth(t: float, fleet: str = "f") -> GroundTruth:
    return GroundTruth(
        fleet=fleet,
        sender="world",
        seq=int(round(t * 10)),
        t_meas=t,
        t_sent=t,
        vehicle_ids=["cv0", "cv1"],
        vehicle_pose=np.array([[t * 5, 0, 0, 0, 0, 0], [t * 5, 20, 0, 0, 0, 0.1]], np.float32),
        vehicle_v_map=np.array([[5, 0, 0], [5, 0, 0]], np.float32),
        obstacle_id=np.array([1], np.uint32),
        obstacle_cls=np.array([1], np.uint8),
        obstacle_p_map=np.array([[20 + t, 0, 0]], np.float32),
        obstacle_v_map=np.array([[1, 0, 0]], np.float32),
        obstacle_yaw=np.array([0], np.float32),
    )


def att(**fields) -> bytes:
    return msgpack.packb(fields, use_bin_type=True)


def write(path: Path, items, **kw) -> RecordingWriter:
    w = RecordingWriter(path, **kw)
    for key, payload, attachment, t_ns in items:
        assert w.add(key, payload, attachment, t_ns)
    w.close()
    return w


def test_every_message_is_kept_byte_for_byte_with_its_attachment_and_times(tmp_path: Path, capsys) -> None:
    t0 = 1_700_000_000_000_000_000
    items = []
    for k in range(30):
        tr = encode(truth(0.1 * k))
        items.append(
            ("mc/f/sim/truth", tr, att(t_wall_ns=t0 + k * 100_000_000 - 5_000, epoch_wall_ns=t0), t0 + k * 10**8)
        )
        items.append((f"mc/f/health/vehicle/cv{k % 2}", b"\x81\x00\x04", None, t0 + k * 10**8 + 1))
    path = tmp_path / "r.mcap"
    write(path, items, viz=visualizer())
    got = list(read_records(path))
    assert [(r.key, r.payload, r.attachment, r.log_time_ns) for r in got] == items
    assert got[0].publish_time_ns == t0 - 5_000  # the publisher's t_wall_ns
    assert got[1].publish_time_ns == got[1].log_time_ns  # no attachment: the log time

    # the mcap package's own reader sees one channel per key, our schemas and Foxglove's
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = {s.id: s for s in summary.schemas.values()}
        assert {"mc/f/sim/truth", "mc/f/health/vehicle/cv0", "mc/f/health/vehicle/cv1"} <= set(channels)
        ch = channels["mc/f/sim/truth"]
        assert ch.message_encoding == "msgpack" and schemas[ch.schema_id].name == "GroundTruth"
        assert json.loads(schemas[ch.schema_id].data)["title"] == "GroundTruth"
        assert channels["/viz/truth"].message_encoding == "json"
        assert schemas[channels["/viz/truth"].schema_id].name == "foxglove.SceneUpdate"
        assert summary.statistics.channel_message_counts[ch.id] == 30
        viz = [json.loads(m.data) for _, c, m in reader.iter_messages(topics=["/viz/truth"])]
    cubes = viz[3]["entities"][0]["cubes"]
    assert len(viz) == 30 and len(cubes) == 2 and cubes[0]["pose"]["position"]["x"] == pytest.approx(1.5)
    assert viz[3]["entities"][0]["frame_id"] == "map" and set(cubes[0]["color"]) == set("rgba")

    doc = info(path)
    assert doc["complete"] and doc["keys"] == 3 and doc["messages"] == 60
    assert doc["duration_s"] == pytest.approx(2.9, abs=1e-6)
    # the keys and the channels counted apart, adding up: mapc record info said "23 keys" over 45 channels
    kinds = doc["channels_by_kind"]
    assert kinds["key"] == doc["keys"] == 3 and sum(kinds.values()) == len(doc["channels"])
    assert kinds["viz"] == sum(c["topic"].startswith("/viz/") for c in doc["channels"]) > 0
    from services.recording_cli import _print_info

    _print_info(doc, as_json=False)
    out = capsys.readouterr().out.splitlines()
    assert out[1] == "  3 fleet keys: 60 messages, " + f"{doc['payload_bytes'] / 1e6:.2f} MB of payload"
    assert out[2].startswith(f"  {len(doc['channels'])} channels: 3 keys, {kinds['attachment']} of their Zenoh")


def test_a_signed_key_is_recorded_as_a_secured_message_naming_the_model_inside(tmp_path: Path) -> None:
    from unit.test_fusion_container import prior

    ca = make_ca("ca", now=time.time() - 60)
    signer = Signer(issue(ca, "cv1", 3600, time.time() - 60))
    path = tmp_path / "s.mcap"
    payload = signer.sign(encode(prior(sender="cv1")), time.time())
    write(path, [("mc/f/v2x/rx/host/cv1/prior", payload, None, time.time_ns())])
    (ch,) = info(path)["channels"]
    assert ch["schema"] == "SecuredMessage" and ch["metadata"]["inner_model"] == "VehiclePrior"
    assert decode(next(read_records(path)).payload, SecuredMessage)


def test_a_file_at_its_size_bound_is_finished_and_takes_no_more(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    w = RecordingWriter(path, max_bytes=400_000, chunk_bytes=50_000, compression="none")
    rng = np.random.default_rng(0)
    added = 0
    while w.add("mc/f/sim/truth", rng.bytes(3000), None, 1 + added):
        added += 1
    assert w.full and w.closed and not w.add("mc/f/sim/truth", b"x", None, 10**9)
    assert path.stat().st_size <= 400_000 and 95 < added < 134  # the rest: chunk indexes and the schemas
    doc = info(path)
    assert doc["complete"] and doc["messages"] == added


def test_a_file_cut_short_is_read_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    w = RecordingWriter(path, chunk_bytes=20_000)
    rng = np.random.default_rng(1)
    for k in range(200):
        w.add("mc/f/sim/truth", bytes([k]) + rng.bytes(1000), att(k=k), 10**9 + k)  # incompressible
        if k % 50 == 49:
            w.flush()
    w.close()
    data = path.read_bytes()
    cut = tmp_path / "cut-short.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    doc = info(cut)
    recs = list(read_records(cut))
    assert not doc["complete"] and doc["stopped"]
    assert 50 <= len(recs) < 200 and [r.payload[0] for r in recs] == list(range(len(recs)))
    # a chunk may end between a payload and its attachment: the last message read may lack it
    assert all(msgpack.unpackb(r.attachment)["k"] == i for i, r in enumerate(recs[:-1]))
    assert recs[-1].attachment in (None, att(k=len(recs) - 1))


def test_bytes_after_the_footer_are_named_not_called_complete(tmp_path: Path) -> None:
    """The probe: 2 KB of junk appended to a finished recording, and `record info` called it complete."""
    path = tmp_path / "grown.mcap"
    write(path, [("mc/f/sim/truth", encode(truth(1.0)), None, 10**18)])
    assert info(path)["complete"] and info(path)["trailing_bytes"] == 0
    with open(path, "ab") as f:
        f.write(bytes(range(256)) * 8)
    doc = info(path)
    assert not doc["complete"] and doc["trailing_bytes"] == 2048 and "2048 bytes follow the footer" in doc["stopped"]
    assert len(list(read_records(path))) == 1  # what the recorder wrote still reads
    out = subprocess.run([sys.executable, "-m", "services.cli", "record", "info", str(path)], capture_output=True,
                         text=True, cwd=REPO, timeout=60)  # fmt: skip
    assert out.returncode == 0 and "APPENDED TO: 2048 bytes follow the footer" in out.stdout, out.stdout + out.stderr


@pytest.mark.parametrize("content", [b"", b"hello, not a recording\n", b"PK\x03\x04" + bytes(100)])
def test_not_an_mcap_file_is_one_line_and_exit_2(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="not an MCAP file"):
        info(path)
    for cmd in (["record", "info", str(path)], ["replay", str(path), "--refuse", "--out", str(tmp_path / "o")]):
        r = subprocess.run([sys.executable, "-m", "services.cli", *cmd], capture_output=True, text=True, cwd=REPO)
        assert r.returncode == 2, r.stderr
        assert r.stderr.count("\n") == 1 and "not an MCAP file" in r.stderr and "Traceback" not in r.stderr


def test_retarget_changes_only_the_fleet_and_the_clock_moves_with_the_replay() -> None:
    from unit.test_fusion_container import prior

    raw = encode(prior(fleet="rec"))
    moved = retarget(raw, "other")
    assert decode(moved, type(prior())).fleet == "other"
    assert decode(moved, type(prior())).model_dump(exclude={"fleet"}) == decode(raw, type(prior())).model_dump(
        exclude={"fleet"}
    )
    assert retarget(b"\x00not ours", "other") == b"\x00not ours"
    a = shift_attachment(att(epoch_wall_ns=1000, t_wall_ns=5000, time_scale=1.0, link_latency_s=0.02), 4000, 10**6, 2.0)
    obj = msgpack.unpackb(a)
    # the replay starts at 1e6 ns for the recording's 4000 ns, twice as fast: scenario times stay the same
    assert obj == {"epoch_wall_ns": 10**6 - 1500, "t_wall_ns": 10**6 + 500, "time_scale": 2.0, "link_latency_s": 0.02}
    t_rec = (5000 - 1000) * 1e-9 * 1.0
    assert (obj["t_wall_ns"] - obj["epoch_wall_ns"]) * 1e-9 * obj["time_scale"] == pytest.approx(t_rec)
    # the message's own clock (what the services read) moves the same way; a message without one is unchanged
    clocked = prior(fleet="rec").model_copy(update={"epoch_wall_ns": 1000, "time_scale": 1.0, "t_next": 0.5})
    m = decode(shift_clock(encode(clocked), 4000, 10**6, 2.0), type(prior()))
    assert (m.epoch_wall_ns, m.time_scale, m.t_next) == (10**6 - 1500, 2.0, 0.5)
    clock = {"epoch_wall_ns", "time_scale"}
    assert m.model_dump(exclude=clock) == clocked.model_dump(exclude=clock)
    assert shift_clock(raw, 4000, 10**6, 2.0) == raw and shift_clock(b"\x00not ours", 0, 1, 1.0) == b"\x00not ours"


def test_an_ellipsoid_has_the_covariance_axes_at_two_sigma() -> None:
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # 90 degrees about z
    C = R @ np.diag([4.0, 1.0, 0.25]) @ R.T
    e = ellipsoid([1, 2, 3], C, (1, 0, 0, 1))
    sizes = sorted([e["size"]["x"], e["size"]["y"], e["size"]["z"]])
    assert sizes == pytest.approx([2.0, 4.0, 8.0])  # 2 * 2 sigma
    q = e["pose"]["orientation"]
    assert q["x"] ** 2 + q["y"] ** 2 + q["z"] ** 2 + q["w"] ** 2 == pytest.approx(1.0)
    assert e["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 3.0}


def test_the_map_scene_holds_every_lane_line_and_landmark() -> None:
    from mapcontainer.hdmap.generator import generate_map
    from mapcontainer.sim.config import load_scenario

    hdmap = generate_map(load_scenario("paper-urban").map)
    doc = json.loads(map_scene(hdmap, 10**18))
    lanes, marks = doc["entities"]
    assert len(lanes["lines"]) == len(hdmap.lane_lines) and len(marks["lines"]) == len(hdmap.poles) == 14
    assert len(marks["spheres"]) == len(hdmap.points) == 8
    assert json.loads(SCENE_UPDATE[1])["title"] == "foxglove.SceneUpdate"


def _host_run(tmp_path: Path, frames: int = 25, fakes: bool = False):
    """A host's fusion loop (services.host.worker, in a thread) fed signed priors of two vehicles; what it
    ingested and published written as a recorder would: the signed payloads on their rx keys, the fused
    states with the attachment the host service gives them, signed as the service signs them. ``fakes``:
    an attacker's fused state (the real one 20 m off, unsigned) on the host's key after each."""
    from services.host.worker import fusion_loop
    from unit.test_fusion_container import prior

    now = time.time()
    ca = make_ca("ca", now=now - 60)
    signers = {v: Signer(issue(ca, v, 3600, now - 60)) for v in ("cv0", "cv1", "host", "world")}
    (tmp_path / "ca.cert.json").write_text(ca.certificate.model_dump_json())
    setup = HostSetup(fleet="f", known_senders=("cv0", "cv1"))
    inbox, outbox = queue.Queue(), queue.Queue()
    th = threading.Thread(target=fusion_loop, args=(setup, inbox, outbox), daemon=True)
    th.start()
    assert outbox.get(timeout=60)[0] == "ready"
    path = tmp_path / "host.mcap"
    w = RecordingWriter(path, files={"ca.cert.json": (tmp_path / "ca.cert.json").read_bytes()})
    fused = []
    start_ns = time.time_ns()  # the world's epoch; messages logged as arriving 30 ms after their frame
    for k in range(frames):
        t = 0.1 * k
        t_ns = start_ns + int(t * 1e9)
        for v, y in (("cv0", 0.0), ("cv1", 12.0)):
            obj = ((20.0 - 0.5 * t, -y, 0.0), (15.0, 3.0 - y, 0.0))
            p = prior(sender=v, seq=k, t=t, pose=(5 * t, y, 0, 0, 0, 0), objects=obj)
            inner = encode(p.model_copy(update={"epoch_wall_ns": start_ns, "time_scale": 1.0}))  # the world's clock
            signed = signers[v].sign(inner, time.time())
            w.add(f"mc/f/v2x/rx/host/{v}/prior", signed, att(t_wall_ns=t_ns), t_ns + 30_000_000)
            inbox.put(("ingest", inner, t + 0.03))
        while True:
            item = outbox.get(timeout=30)
            if item[0] == "fused":
                break
        _, payload, t_f, _, _, solved, _, _ = item
        signed = signers["host"].sign(payload, time.time())  # the host service signs its fused state
        w.add("mc/f/host/host/fused", signed, att(t_wall_ns=t_ns + 60_000_000, t_fused=t_f, **solved), t_ns + 60_000_000)
        w.add("mc/f/sim/truth", signers["world"].sign(encode(truth(t)), time.time()), None, t_ns + 70_000_000)
        if fakes:
            real = decode(payload, FusedState)
            fake = real.model_copy(update={"vehicle_pose": real.vehicle_pose + np.float32(20.0), "seq": real.seq + 1000})
            w.add("mc/f/host/host/fused", encode(fake), None, t_ns + 65_000_000)
        fused.append(payload)
    inbox.put(("stop",))
    th.join(timeout=10)
    w.close()
    return path, fused


def test_refusing_with_the_recorded_parameters_reproduces_the_fused_states_byte_for_byte(tmp_path: Path) -> None:
    """The host publishes the input set of every solve; re-fusion ingests exactly those and solves at the same
    times, so the states are the same bytes (no tolerance: the container is deterministic)."""
    path, fused = _host_run(tmp_path)
    setup = HostSetup(fleet="f", known_senders=("cv0", "cv1"))
    res = refuse(path, setup=setup)
    assert res.signatures_verified and res.signature_refused == 0 and res.ingested == 50
    assert res.compared == len(fused) == 25 and res.identical == 25 and res.max_abs_diff == 0.0
    assert [encode(s) for s in res.fused] == fused
    assert any(len(s.object_id) for s in res.fused)  # tracks were fused, not only poses
    assert res.scores["refused"] == res.scores["recorded"] and res.scores["refused"]["whole"]["frames"] == 25

    other = refuse(path, setup=setup, params={"window_s": 0.3})  # another parameter set, side by side
    assert other.compared == 25 and other.identical < 25
    arrival = refuse(path, setup=setup, schedule="arrival")  # the frame gate on the recorded arrivals
    assert len(arrival.fused) >= 20 and arrival.scores["refused"]["whole"]["frames"] >= 20


def test_replay_unwraps_verified_signed_messages_onto_the_target_fleet(tmp_path: Path) -> None:
    path, _ = _host_run(tmp_path, frames=5)
    items, fig = replay_plan(path, "other", speed=2.0, topics=("prior_rx", "truth"))
    assert fig["signatures_verified"] and fig["refused_signatures"] == 0 and fig["messages"] == 15
    assert all(it.key.startswith("mc/other/") for it in items)
    assert [it.at_s for it in items] == sorted(it.at_s for it in items)
    rx = [it for it in items if topic("prior_rx").parse(it.key)]
    assert all(peek(it.payload)["fleet"] == "other" and "payload" not in peek(it.payload) for it in rx)
    assert not any(topic("fused").parse(it.key) for it in items)
    assert isinstance(decode(items[-1].payload, GroundTruth), GroundTruth)
    assert decode(rx[0].payload, VehiclePrior).sender == "cv0"


def test_the_recorded_host_setup_comes_from_the_runs_config(tmp_path: Path) -> None:
    """Read back with the host's own flags; the service's transport flags and those of older hosts
    (``--scenario``, ``--seed``) are not the container's."""
    from mapcontainer.recording.replay import host_setup

    (tmp_path / "p.yaml").write_text("window_s: 0.5\n")
    argv = ["python", "-m", "services.host", "--scenario", "overlap", "--seed", "7", "--mode", "centralized",
            "--map", "run/map.geojson", "--local", "cv0", "--known-senders", "cv0,cv1", "--fleet", "run1",
            "--id", "host", "--connect", "tcp/127.0.0.1:7447", "--params", str(tmp_path / "p.yaml")]  # fmt: skip
    standby = [*argv, "--standby-for", "host"]
    config = {"processes": [{"role": "host", "argv": standby}, {"role": "host", "argv": argv}]}
    path = tmp_path / "c.mcap"
    w = RecordingWriter(path, metadata={"fleet": "run1"}, files={"config.json": json.dumps(config).encode()})
    w.close()
    s = host_setup(path)
    assert (s.fleet, s.host_id, s.mode, s.map_file, s.local, s.known_senders, s.params.window_s) == (
        "run1", "host", "centralized", "run/map.geojson", ("cv0",), ("cv0", "cv1"), 0.5
    )  # fmt: skip
    with pytest.raises(RecordingError, match="needs its HD map"):  # the run's map is not where it was
        refuse(path)
    bare = tmp_path / "bare.mcap"
    RecordingWriter(bare).close()
    with pytest.raises(RecordingError, match="which fleet"):
        host_setup(bare)


@pytest.mark.parametrize("damage", ["corrupt", "header-only"])
def test_a_corrupt_file_or_one_cut_before_any_record_is_one_line_and_exit_2(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "ok.mcap"
    w = RecordingWriter(path, chunk_bytes=20_000)
    rng = np.random.default_rng(2)
    for k in range(100):
        w.add("mc/f/sim/truth", rng.bytes(1000), None, 10**9 + k)
    w.close()
    data = bytearray(path.read_bytes())
    if damage == "corrupt":
        data[len(data) // 3] ^= 0xFF  # inside a chunk: its CRC fails, with whole chunks after it
        match = "corrupt at byte"
    else:
        data = data[:12]
        match = "cut off before its first record"
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=match):
        info(bad)
    r = subprocess.run(
        [sys.executable, "-m", "services.cli", "record", "info", str(bad)], capture_output=True, text=True, cwd=REPO
    )
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and match in r.stderr, r.stderr


def test_a_restarted_recorder_continues_beside_the_first_file_and_readers_follow(tmp_path: Path) -> None:
    from mapcontainer.recording import recording_files
    from mapcontainer.recording.replay import replay_plan
    from services.recorder.app import free_path

    first = tmp_path / "recording.mcap"
    for k in range(3):
        path = free_path(first)
        write(path, [("mc/f/sim/truth", encode(truth(0.1 * k)), None, 10**18 + k * 10**8)])
    assert [p.name for p in recording_files(first)] == ["recording.mcap", "recording-1.mcap", "recording-2.mcap"]
    items, fig = replay_plan(first, "g", topics=("truth",))
    assert [decode(it.payload, GroundTruth).seq for it in items] == [0, 1, 2]
    assert [it.at_s for it in items] == pytest.approx([0.0, 0.1, 0.2])


def test_the_point_clouds_are_foxglove_protobuf_with_their_descriptors(tmp_path: Path) -> None:
    """What Rerun's MCAP import turns into Points3D: foxglove.PointCloud in Protobuf, schema a FileDescriptorSet."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from google.protobuf import descriptor_pb2

    path = tmp_path / "p.mcap"
    write(path, [("mc/f/sim/truth", encode(truth(1.0)), None, 10**18)], viz=visualizer())
    with open(path, "rb") as f:
        reader = make_reader(f)
        ((schema, channel, message),) = list(reader.iter_messages(topics=["/viz/points/truth"]))
    assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
    assert schema.name == "foxglove.PointCloud"
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data).file
    assert "foxglove/PointCloud.proto" in {f.name for f in files}
    pc = PointCloud.FromString(message.data)
    assert pc.frame_id == "map" and pc.point_stride == 16 and [f.name for f in pc.fields][:3] == ["x", "y", "z"]
    rec = np.frombuffer(pc.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    assert len(rec) == 3  # two vehicles, one obstacle
    assert rec["xyz"][2] == pytest.approx([21.0, 0.0, 0.0]) and rec["rgba"][0].tolist() == [26, 204, 51, 153]


def test_a_fake_fused_state_on_the_hosts_key_is_refused_by_every_reader_of_the_recording(tmp_path: Path) -> None:
    """The probe's fake fused state (+20 m) on the host's own key: the re-fusion check, the recorder's
    Foxglove channels and the view refuse it (not signed by the host) and count it; the recorded host's
    score is the genuine one."""
    from mapcontainer.recording.replay import _verifier

    frames = 8
    path, fused = _host_run(tmp_path, frames=frames, fakes=True)
    setup = HostSetup(fleet="f", known_senders=("cv0", "cv1"))
    res = refuse(path, setup=setup)
    assert res.signature_refused == frames and res.compared == frames and res.identical == frames
    assert res.scores["recorded"] == res.scores["refused"]
    records = list(read_records(path))
    refused: dict[str, int] = {}
    viz = visualizer(_verifier(path), refused)
    drawn = [ch for r in records for ch, *_ in viz(r.key, r.payload, r.log_time_ns) if ch == "/viz/fused/host"]
    assert len(drawn) == frames and refused == {"unsigned": frames}
    unverified: dict[str, int] = {}
    assert len([1 for r in records for ch, *_ in visualizer(None, unverified)(r.key, r.payload, r.log_time_ns)
                if ch == "/viz/fused/host"]) == 2 * frames and unverified == {}  # fmt: skip


def test_the_view_draws_only_what_the_fleet_signed(tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun", reason="mapc view needs the view extra (rerun-sdk)")
    from mapcontainer.recording.replay import _verifier
    from mapcontainer.recording.view import RerunView

    frames = 5
    path, _ = _host_run(tmp_path, frames=frames, fakes=True)
    view = RerunView(rr.RecordingStream("test-view"), _verifier(path))
    for r in read_records(path):
        view.handle(r.key, r.payload, r.log_time_ns)
    assert view.drawn["fused"] == frames and view.drawn["truth"] == frames and view.refused == {"unsigned": frames}
