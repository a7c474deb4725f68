"""Wall-clock instrumentation in Zenoh attachments, and the world's clock as another service sees it
(:class:`mapcontainer.clock.SimClock`, the same rules in process and in replay)."""

from __future__ import annotations

from typing import Any

import msgpack

from mapcontainer.clock import SimClock

__all__ = ["SimClock", "make_attachment", "read_attachment"]

# ------------------------------------------------------------------------------ attachments


def make_attachment(**fields: int | float | str | None) -> bytes:
    """A msgpack map of instrumentation fields (None values left out)."""
    return msgpack.packb({k: v for k, v in fields.items() if v is not None}, use_bin_type=True)


def read_attachment(sample_or_bytes) -> dict[str, Any]:
    """The attachment map of a sample (or raw attachment bytes); {} if absent or unreadable."""
    att = getattr(sample_or_bytes, "attachment", sample_or_bytes)
    if att is None:
        return {}
    try:
        raw = att.to_bytes() if hasattr(att, "to_bytes") else bytes(att)
        obj = msgpack.unpackb(raw, raw=False)
    except Exception:  # instrumentation only: a bad attachment is ignored, never fatal
        return {}
    if not isinstance(obj, dict):
        return {}
    return {k: v for k, v in obj.items() if isinstance(k, str)}  # names only: fields are passed on as keywords
