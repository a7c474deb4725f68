"""An MCAP file of a fleet's messages: :class:`RecordingWriter`, :func:`read_records`, :func:`info`.

Layout of a recording (profile ``mapcontainer``):

* one channel per Zenoh key, its topic the key itself (``mc/local/v2x/rx/host/cv1/prior``), holding
  the **exact payload bytes** as they travelled, message encoding ``msgpack``. MCAP's well-known
  encodings have no msgpack and pair the ``jsonschema`` schema encoding with JSON messages, so the
  channel's schema is our JSON Schema of the model (``schemas/json/``, which names every field's
  integer tag as ``x-tag``) under the schema encoding ``x-mapcontainer-jsonschema+msgpack``: a reader
  that does not know it still lists the channel, its counts and the schema's text, and our code
  decodes the bytes. Signed V2X keys carry a ``SecuredMessage`` (its schema says so; the channel
  metadata's ``inner_model`` names the message inside). Channel metadata: ``topic`` (the registry
  name), ``model``, ``inner_model``.
* beside it the channel ``<key>#attachment``: the message's Zenoh attachment bytes (a msgpack map
  of clock and latency fields), with the same MCAP ``sequence`` number as its payload record, written
  right after it. Attachments vary per message (the world's clock, the publish wall time), so they
  cannot live in the channel's static metadata; a parallel channel keeps them byte for byte.
* ``log_time``: the recorder's receive wall time (Unix ns); ``publish_time``: the publisher's
  ``t_wall_ns`` from the attachment when it carries one, else the log time.
* visualization channels under ``/viz/...`` in Foxglove's JSON schemas (:mod:`.foxglove`).
* MCAP attachments: ``ca.cert.json`` (the fleet CA's public certificate, to verify the signed messages
  offline), ``config.json`` (the run's resolved configuration), when given; MCAP metadata ``recording``
  (fleet, scenario, seed, ...).

The writer finishes a chunk at ``chunk_bytes`` and whenever :meth:`RecordingWriter.flush` is called
(the recorder does so every second), so a recorder killed with SIGKILL leaves a file readable up to
its last finished chunk: :func:`read_records` streams records and stops at the first incomplete one
(the last message read may lack its attachment, when a chunk ended between the two).
A file reaching ``max_bytes`` is finished (summary and footer written) and takes no more messages.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from schemas.codec import peek
from schemas.export import DEFAULT_DIR, schema_filename
from schemas.models import SecuredMessage
from schemas.topics import TOPICS, Topic

__all__ = [
    "ATTACHMENT_SUFFIX",
    "PROFILE",
    "RAW_ENCODING",
    "RAW_SCHEMA_ENCODING",
    "Record",
    "RecordingError",
    "RecordingWriter",
    "info",
    "read_records",
    "recording_files",
    "topic_of",
]

PROFILE = "mapcontainer"
RAW_ENCODING = "msgpack"
RAW_SCHEMA_ENCODING = "x-mapcontainer-jsonschema+msgpack"
ATTACHMENT_SUFFIX = "#attachment"
MAGIC = b"\x89MCAP0\r\n"
_ATTACHMENT_SCHEMA = {
    "title": "mapcontainer.Attachment",
    "description": "The Zenoh attachment of the message with the same sequence number on the key's own channel: "
    "a msgpack map of instrumentation fields (string keys), e.g. epoch_wall_ns and time_scale (the world's "
    "clock: t = (wall_ns - epoch_wall_ns) * 1e-9 * time_scale), t_wall_ns (publish wall time), t_fused and "
    "inputs (the host: the time it solved and the (sender, seq, t_recv) of every message ingested for it).",
    "type": "object",
}


class RecordingError(ValueError):
    """A file that is not a recording we can read (not MCAP, or broken before its first message)."""


def topic_of(key: str) -> Topic | None:
    """The registry entry whose template ``key`` matches, or None."""
    for t in TOPICS:
        if t.parse(key) is not None:
            return t
    return None


def _model_schema(model: type) -> bytes:
    """The exported JSON Schema of a wire model (schemas/json/, package data)."""
    path = Path(DEFAULT_DIR) / schema_filename(model)
    return path.read_bytes() if path.exists() else json.dumps({"title": model.__name__, "type": "object"}).encode()


@dataclass(frozen=True)
class Record:
    """One recorded message: its key, payload and attachment bytes, times (Unix ns) and sequence."""

    key: str
    payload: bytes
    attachment: bytes | None
    log_time_ns: int
    publish_time_ns: int
    sequence: int


class RecordingWriter:
    """Writes a fleet's messages to an MCAP file; see the module docstring for the layout.

    ``viz``: a callable ``(key, payload, log_time_ns) -> [(topic, schema_name, schema_json, data)]``
    giving the visualization messages of a message (:func:`mapcontainer.recording.foxglove.visualizer`),
    or None. ``add`` returns False once the file is full (``max_bytes``), and the file is then finished.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        max_bytes: int = 2 * 1024**3,
        chunk_bytes: int = 256 * 1024,
        metadata: dict[str, str] | None = None,
        files: dict[str, bytes] | None = None,
        viz: Callable[[str, bytes, int], list[tuple[str, str, bytes, bytes]]] | None = None,
        compression: str = "zstd",
    ):
        if max_bytes < 4 * chunk_bytes:
            raise ValueError(f"max_bytes {max_bytes} must be at least 4 chunks ({4 * chunk_bytes} bytes)")
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.chunk_bytes = int(chunk_bytes)
        # flush() hands everything to the kernel: what was flushed survives a SIGKILL of this process
        self._file = open(self.path, "xb")  # noqa: SIM115 (closed in close())
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._w = Writer(self._file, chunk_size=self.chunk_bytes, compression=comp)
        self._w.start(profile=PROFILE, library="mapcontainer")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._viz = viz
        self.messages = 0
        self.full = False
        self.closed = False
        if metadata:
            self._w.add_metadata("recording", {k: str(v) for k, v in metadata.items()})
        for name, data in (files or {}).items():
            self._w.add_attachment(0, 0, name, "application/json", data)

    # ------------------------------------------------------------------ channels
    def _schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = self._schemas.get((name, encoding))
        if sid is None:
            sid = self._schemas[(name, encoding)] = self._w.register_schema(name, encoding, data)
        return sid

    def _channel(self, key: str, payload: bytes) -> int:
        cid = self._channels.get(key)
        if cid is not None:
            return cid
        tp = topic_of(key)
        meta: dict[str, str] = {}
        if tp is not None and tp.model is not None:
            model = tp.model
            meta = {"topic": tp.name, "model": model.__name__}
            if isinstance(peek(payload).get("payload"), bytes):  # signed: a SecuredMessage around the model
                meta.update(model=SecuredMessage.__name__, inner_model=model.__name__)
                model = SecuredMessage
            sid = self._schema(model.__name__, RAW_SCHEMA_ENCODING, _model_schema(model))
        else:
            sid = 0
        cid = self._channels[key] = self._w.register_channel(key, RAW_ENCODING, sid, meta)
        return cid

    def _attachment_channel(self, key: str) -> int:
        topic = key + ATTACHMENT_SUFFIX
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schema("mapcontainer.Attachment", RAW_SCHEMA_ENCODING, json.dumps(_ATTACHMENT_SCHEMA).encode())
            cid = self._channels[topic] = self._w.register_channel(topic, RAW_ENCODING, sid, {"attachment_of": key})
        return cid

    def _viz_channel(self, topic: str, schema_name: str, schema: bytes) -> int:
        """A visualization channel: JSON with a JSON Schema, or Protobuf when the schema is a FileDescriptorSet."""
        cid = self._channels.get(topic)
        if cid is None:
            proto = not schema.lstrip().startswith(b"{")
            sid = self._schema(schema_name, "protobuf" if proto else "jsonschema", schema)
            cid = self._channels[topic] = self._w.register_channel(topic, "protobuf" if proto else "json", sid, {})
        return cid

    # ------------------------------------------------------------------ writing
    @property
    def bytes_written(self) -> int:
        """Bytes in the file so far (finished chunks; the chunk being filled is not counted)."""
        return self._file.tell() if not self._file.closed else self.path.stat().st_size

    def add(self, key: str, payload: bytes, attachment: bytes | None, log_time_ns: int) -> bool:
        """Record one message; False (and nothing written) once the file is full or closed."""
        if self.full or self.closed:
            return False
        if self._file.tell() + 2 * self.chunk_bytes + len(payload) > self.max_bytes:
            self.full = True
            self.close()
            return False
        cid = self._channel(key, payload)
        seq = self._seq[key] = self._seq.get(key, -1) + 1
        publish = log_time_ns
        if attachment:
            t_pub = _attachment_wall_ns(attachment)
            publish = t_pub if t_pub is not None else log_time_ns
        self._w.add_message(cid, log_time_ns, payload, publish, seq & 0xFFFFFFFF)
        if attachment is not None:
            self._w.add_message(self._attachment_channel(key), log_time_ns, attachment, publish, seq & 0xFFFFFFFF)
        self.messages += 1
        if self._viz is not None:
            for topic, schema_name, schema, data in self._viz(key, payload, log_time_ns):
                self._w.add_message(self._viz_channel(topic, schema_name, schema), log_time_ns, data, log_time_ns, 0)
        return True

    def add_viz(self, topic: str, schema_name: str, schema: bytes, data: bytes, log_time_ns: int) -> None:
        """A visualization message of its own (e.g. the map, once)."""
        if not (self.full or self.closed):
            self._w.add_message(self._viz_channel(topic, schema_name, schema), log_time_ns, data, log_time_ns, 0)

    def flush(self) -> None:
        """Finish the chunk being filled and hand it to the kernel (what survives a killed recorder)."""
        if not self.closed:
            self._w.flush()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._w.finish()
            self._file.flush()
        finally:
            self._file.close()


def _attachment_wall_ns(attachment: bytes) -> int | None:
    import msgpack

    try:
        obj = msgpack.unpackb(attachment, raw=False)
    except Exception:  # an attachment is instrumentation: unreadable means no publish time
        return None
    t = obj.get("t_wall_ns") if isinstance(obj, dict) else None
    return t if type(t) is int and 0 < t < 2**63 else None


def recording_files(path: str | Path) -> list[Path]:
    """``path`` and the files a restarted recorder continued in (``NAME-1.mcap``, ``NAME-2.mcap`` ...)."""
    path = Path(path)
    out = [path]
    k = 1
    while (p := path.with_name(f"{path.stem}-{k}{path.suffix}")).exists():
        out.append(p)
        k += 1
    return out


# ---------------------------------------------------------------------------- reading


@dataclass
class Scan:
    """What :func:`scan` found in a file: every record it could read, and whether the file ended cleanly."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    attachments: list[Attachment] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    profile: str = ""
    complete: bool = False  # a footer was read and nothing follows it: the writer finished the file
    stopped: str | None = None  # why reading stopped early (a killed writer's last, incomplete chunk)
    trailing_bytes: int = 0  # bytes after the footer's closing magic (appended by something else)


def _stream(path: Path, scan: Scan, on_message: Callable[[Channel, Message], None]) -> None:
    """Read every record of ``path`` in file order. A file that ends inside a record (a writer killed
    before finishing its chunk) stops there, ``scan.stopped`` saying so; a record that fails its CRC or
    does not decode with bytes after it is corruption: RecordingError, as is a file that is not MCAP."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
        if head != MAGIC:
            raise RecordingError(f"{path}: not an MCAP file (it starts with {head[:8]!r})")
        f.seek(0)
        reader = StreamReader(f, validate_crcs=True)
        try:
            for rec in reader.records:
                if isinstance(rec, Message):
                    ch = scan.channels.get(rec.channel_id)
                    if ch is not None:
                        on_message(ch, rec)
                elif isinstance(rec, Channel):
                    scan.channels[rec.id] = rec
                elif isinstance(rec, Schema):
                    scan.schemas[rec.id] = rec
                elif isinstance(rec, Attachment):
                    scan.attachments.append(rec)
                elif isinstance(rec, Metadata):
                    scan.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    scan.complete = True
                elif isinstance(rec, DataEnd | Chunk):
                    pass
                elif type(rec).__name__ == "Header":
                    scan.profile = rec.profile
            if scan.complete and f.tell() < size:  # a finished file does not grow: someone appended to it
                scan.trailing_bytes = size - f.tell()
                scan.complete = False
                scan.stopped = f"{scan.trailing_bytes} bytes follow the footer (not written by the recorder)"
        except Exception as exc:  # mcap, struct, zlib, zstandard and lz4 errors alike: where, decides what it is
            what = f"{type(exc).__name__}: {exc}".strip(": ")[:160]
            if f.tell() < size:
                raise RecordingError(f"{path}: corrupt at byte {f.tell()} of {size} ({what})") from None
            if not scan.profile:
                raise RecordingError(f"{path}: cut off before its first record ({size} bytes)") from None
            scan.stopped = f"the file ends inside a record at byte {size} (its recorder was killed?): {what}"


def read_records(
    path: str | Path, keys: Callable[[str], bool] | None = None, scan: Scan | None = None
) -> Iterator[Record]:
    """The recorded messages of ``path`` in file order (the order they were recorded), each with its
    attachment; ``keys`` filters by key. Reads a file whose writer was killed up to its last finished
    chunk (``scan.stopped`` says where it stopped). Raises RecordingError for a file that is not MCAP."""
    path = Path(path)
    scan = scan if scan is not None else Scan()
    out: list[Record] = []
    pending: dict[str, Message] = {}

    def on_message(ch: Channel, m: Message) -> None:
        topic = ch.topic
        if topic.startswith("/viz/"):
            return
        if topic.endswith(ATTACHMENT_SUFFIX):
            key = topic[: -len(ATTACHMENT_SUFFIX)]
            p = pending.pop(key, None)
            if p is not None and p.sequence == m.sequence:
                out.append(Record(key, p.data, m.data, p.log_time, p.publish_time, p.sequence))
            elif p is not None:
                out.append(Record(key, p.data, None, p.log_time, p.publish_time, p.sequence))
            return
        if keys is not None and not keys(topic):
            return
        prev = pending.pop(topic, None)
        if prev is not None:  # no attachment was recorded for it
            out.append(Record(topic, prev.data, None, prev.log_time, prev.publish_time, prev.sequence))
        pending[topic] = m

    _stream(path, scan, on_message)
    if scan.profile and scan.profile != PROFILE:
        raise RecordingError(f"{path}: an MCAP file of profile {scan.profile!r}, not a {PROFILE} recording")
    for key, p in pending.items():
        out.append(Record(key, p.data, None, p.log_time, p.publish_time, p.sequence))
    out.sort(key=lambda r: r.log_time_ns)  # stable: file order within one log time
    yield from out


def info(path: str | Path) -> dict[str, Any]:
    """Channels (message count, bytes, encoding, schema), messages, duration and bytes of a recording."""
    path = Path(path)
    scan = Scan()
    channels: dict[int, dict[str, Any]] = {}
    t = [None, None]

    def on_message(ch: Channel, m: Message) -> None:
        c = channels.setdefault(ch.id, {"count": 0, "bytes": 0})
        c["count"] += 1
        c["bytes"] += len(m.data)
        t[0] = m.log_time if t[0] is None else min(t[0], m.log_time)
        t[1] = m.log_time if t[1] is None else max(t[1], m.log_time)

    _stream(path, scan, on_message)
    rows = []
    for cid, ch in sorted(scan.channels.items(), key=lambda kv: kv[1].topic):
        c = channels.get(cid, {"count": 0, "bytes": 0})
        schema = scan.schemas.get(ch.schema_id)
        kind = (
            "viz" if ch.topic.startswith("/viz/") else "attachment" if ch.topic.endswith(ATTACHMENT_SUFFIX) else "key"
        )
        rows.append(
            {
                "topic": ch.topic,
                "kind": kind,
                "messages": c["count"],
                "bytes": c["bytes"],
                "message_encoding": ch.message_encoding,
                "schema": schema.name if schema else None,
                "metadata": dict(ch.metadata),
            }
        )
    duration = (t[1] - t[0]) * 1e-9 if t[0] is not None else 0.0
    size = path.stat().st_size
    data = [r for r in rows if r["kind"] == "key"]  # the fleet's Zenoh keys: what a replay publishes
    return {
        "file": str(path),
        "profile": scan.profile,
        "complete": scan.complete,
        "stopped": scan.stopped,
        "trailing_bytes": scan.trailing_bytes,
        "file_bytes": size,
        "start_ns": t[0],
        "end_ns": t[1],
        "duration_s": duration,
        "keys": len(data),
        "channels_by_kind": {k: sum(r["kind"] == k for r in rows) for k in ("key", "attachment", "viz")},
        "messages": sum(r["messages"] for r in data),
        "payload_bytes": sum(r["bytes"] for r in data),
        "records": sum(r["messages"] for r in rows),
        "mb_per_min": size / 1e6 / (duration / 60.0) if duration > 0 else None,
        "attachments": [{"name": a.name, "bytes": len(a.data)} for a in scan.attachments],
        "metadata": scan.metadata,
        "channels": rows,
    }


def attachment_file(path: str | Path, name: str) -> bytes | None:
    """The MCAP attachment ``name`` of a recording (e.g. ``ca.cert.json``), or None."""
    scan = Scan()
    _stream(Path(path), scan, lambda ch, m: None)
    for a in scan.attachments:
        if a.name == name:
            return bytes(a.data)
    return None


def read_scan(path: str | Path) -> Scan:
    """Schemas, channels, attachments and metadata of a recording (messages skipped)."""
    scan = Scan()
    _stream(Path(path), scan, lambda ch, m: None)
    return scan
