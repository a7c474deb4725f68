"""Read any supported map file: ours (GeoJSON), a SUMO network, a Lanelet2 OSM map; tell them apart."""

from __future__ import annotations

import gzip
from pathlib import Path

from .errors import MapFileError
from .imported import ImportedMap
from .io import load_map, load_origin
from .sumo import PlacementRule

__all__ = ["FORMATS", "detect_format", "read_any_map"]

FORMATS = ("geojson", "sumo", "lanelet2")


def detect_format(path: Path) -> str:
    """``geojson``, ``sumo`` or ``lanelet2`` from the name (``.geojson``/``.json``, ``.net.xml[.gz]``, ``.osm``),
    else from the content (gzip or an XML root ``<net>``: SUMO; ``<osm>``: Lanelet2; ``{``: GeoJSON)."""
    name = path.name.lower()
    if name.endswith((".geojson", ".json")):
        return "geojson"
    if name.endswith((".net.xml", ".net.xml.gz")):
        return "sumo"
    if name.endswith(".osm"):
        return "lanelet2"
    if not path.is_file():
        raise MapFileError(f"{path}: no such file")
    with path.open("rb") as fh:
        head = fh.read(4096)
    if not head:
        raise MapFileError(f"{path}: the file is empty")
    if head[:2] == b"\x1f\x8b":
        try:
            with gzip.open(path, "rb") as fh:
                head = fh.read(4096)
        except (OSError, EOFError) as exc:
            raise MapFileError(f"{path}: corrupt gzip data ({exc})") from None
    text = head.lstrip().decode("utf-8", errors="replace")
    if text.startswith("{"):
        return "geojson"
    if "<net" in text:
        return "sumo"
    if "<osm" in text:
        return "lanelet2"
    raise MapFileError(f"{path}: not a map this tool reads (GeoJSON HD map, SUMO .net.xml, Lanelet2 .osm)")


def read_any_map(
    path: Path | str,
    fmt: str = "auto",
    rule: PlacementRule | None = None,
    additional: Path | str | None = None,
    origin=None,
    projector: str = "local",
) -> ImportedMap:
    """The map in ``path`` (``fmt``: ``auto`` or one of :data:`FORMATS`); MapFileError if it cannot be read."""
    path = Path(path)
    fmt = detect_format(path) if fmt == "auto" else fmt
    if fmt == "sumo":
        from .sumo import import_sumo

        return import_sumo(path, rule, additional)
    if fmt == "lanelet2":
        from .lanelet import import_lanelet2

        return import_lanelet2(path, origin, projector)
    if fmt != "geojson":
        raise ValueError(f"format must be 'auto' or one of {FORMATS}, got {fmt!r}")
    if not path.is_file():
        raise MapFileError(f"{path}: no such file")
    try:
        hd = load_map(path)
        return ImportedMap(hd, load_origin(path), f"geojson:{path}")
    except ValueError as exc:  # load_map names the file and the bad feature; undecodable bytes too
        raise MapFileError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
