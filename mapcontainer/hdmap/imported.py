"""What an importer returns: the map, the geodetic position of its origin when known, and notes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .io import MapOrigin
from .model import HDMap

__all__ = ["ImportedMap"]


@dataclass
class ImportedMap:
    """An imported map, the geodetic position of its origin when known, and what the import noticed."""

    hdmap: HDMap
    origin: MapOrigin | None = None
    source: str = ""
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Counts of what the map holds, for the command line and the tests."""
        hd = self.hdmap
        kinds = [ln.kind for ln in hd.lane_lines]
        areas = [w.kind for w in hd.walkable]
        return {
            "name": hd.name,
            "source": self.source,
            "lane_lines": {"solid": kinds.count("solid"), "dashed": kinds.count("dashed")},
            "centerlines": len(hd.centerlines),
            "walkable": {"sidewalk": areas.count("sidewalk"), "crossing": areas.count("crossing")},
            "junctions": len(hd.junctions),
            "landmarks": hd.feature_counts(),
            "origin": None if self.origin is None else vars(self.origin),
            "notes": self.notes,
        }
