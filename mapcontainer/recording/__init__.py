"""Recordings of a fleet's traffic as MCAP files, and their replay: the pure core (no zenoh, no services).

* :mod:`.mcapio` writes every message of a fleet's keys to an MCAP file (the exact payload bytes, the
  Zenoh attachment, log and publish times) and reads it back, also from a file whose writer was killed;
* :mod:`.foxglove` turns truth, fused states and the HD map into Foxglove's JSON schemas, for viewers;
* :mod:`.replay` shifts a recording onto another fleet namespace and clock, and re-fuses its recorded
  vehicle messages in process with the host's core;
* :mod:`.view` draws our messages in Rerun (``mapc view``; needs the ``view`` extra, imported on use).
"""

from .mcapio import (
    ATTACHMENT_SUFFIX,
    RAW_ENCODING,
    Record,
    RecordingError,
    RecordingWriter,
    info,
    read_records,
    recording_files,
)

__all__ = [
    "ATTACHMENT_SUFFIX",
    "RAW_ENCODING",
    "Record",
    "RecordingError",
    "RecordingWriter",
    "info",
    "read_records",
    "recording_files",
]
