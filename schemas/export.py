"""Export the wire contract as JSON Schema files (``schemas/json/``), for readers without our code.

One file per message model, ``<snake_case_name>.json`` (pydantic's serialization-mode JSON Schema;
every property carries its wire tag as ``x-tag`` (:mod:`schemas.tags`), array fields ``x-dtype`` and
``x-shape`` from :mod:`schemas.arrays`), plus ``topics.json``
describing the topic registry. Output is deterministic (sorted keys, indent 2, trailing newline)
so that a test can check the committed files are current: :func:`stale` lists the files that
:func:`export` would change. Regenerate with ``mapc schemas export`` or ``python -m schemas.export``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from .models import SCHEMA_VERSION, SecuredMessage
from .tags import TAGS
from .topics import TOPICS

__all__ = ["DEFAULT_DIR", "MODELS", "export", "render", "schema_filename", "stale"]

DEFAULT_DIR = Path(__file__).parent / "json"

# Every message model that travels on a registered topic, in registry order, then the signed envelope
# that carries a message on the V2X link (SecuredMessage, with its Certificate).
MODELS: tuple[type[BaseModel], ...] = tuple(
    dict.fromkeys([*(t.model for t in TOPICS if t.model is not None), SecuredMessage])
)

_WIRE_NOTE = (
    "Wire format: a msgpack map keyed by each property's integer x-tag, not its name (nested parts too); "
    "absent optional fields mean null/default; fields marked format=binary (and bytes fields) travel as "
    "msgpack bin, arrays little-endian row-major with x-dtype and x-shape. Readers ignore unknown tags. "
    "See schemas/README.md."
)


def schema_filename(model: type[BaseModel]) -> str:
    """``FusedState`` -> ``fused_state.json``."""
    return re.sub(r"(?<!^)(?=[A-Z])", "_", model.__name__).lower() + ".json"


def _dumps(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, indent=2) + "\n"


def _wire_annotations(node: Any) -> None:
    """Append the packing to array fields whose own description replaced the one from arrays.py.

    ``bytes`` fields travel as msgpack bin, not base64 text: their format becomes ``binary``.
    """
    if isinstance(node, dict):
        if node.get("type") == "string" and node.get("format") == "base64url":
            node["format"] = "binary"
        if "x-dtype" in node and "msgpack bin" not in node.get("description", ""):
            packing = f"msgpack bin: {node['x-dtype']} little-endian, row-major, shape {node['x-shape']}"
            node["description"] = f"{node['description']} ({packing})" if node.get("description") else packing
        for value in node.values():
            _wire_annotations(value)
    elif isinstance(node, list):
        for value in node:
            _wire_annotations(value)


def _tag_properties(schema: dict[str, Any]) -> None:
    """``x-tag`` (the wire key) on every property of the model and of its nested parts (``$defs``)."""
    for node in [schema, *schema.get("$defs", {}).values()]:
        for name, prop in node.get("properties", {}).items():
            prop["x-tag"] = TAGS[name]


def _model_schema(model: type[BaseModel]) -> dict[str, Any]:
    schema = model.model_json_schema(mode="serialization")
    _wire_annotations(schema)
    _tag_properties(schema)
    schema["$comment"] = _WIRE_NOTE
    schema["x-schema-version"] = SCHEMA_VERSION
    return schema


def _topics_doc() -> dict[str, Any]:
    return {
        "schema_version": SCHEMA_VERSION,
        "topics": [
            {
                "name": t.name,
                "key": t.template,
                "model": t.model.__name__ if t.model is not None else None,
                "rate_hz": t.rate_hz,
                "description": t.description,
            }
            for t in TOPICS
        ],
    }


def render() -> dict[str, str]:
    """File name -> exact text that :func:`export` writes."""
    files = {schema_filename(m): _dumps(_model_schema(m)) for m in MODELS}
    files["topics.json"] = _dumps(_topics_doc())
    return files


def export(out_dir: Path = DEFAULT_DIR) -> list[Path]:
    """Write every schema file into ``out_dir`` (created if needed); returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in render().items():
        path = out_dir / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written


def stale(out_dir: Path = DEFAULT_DIR) -> list[str]:
    """Names of the files in ``out_dir`` that are missing or differ from what :func:`export` writes."""
    out_dir = Path(out_dir)
    bad = []
    for name, text in render().items():
        path = out_dir / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            bad.append(name)
    return bad


def main(argv: list[str] | None = None) -> int:
    """``python -m schemas.export [OUT_DIR]``: write the files and list them."""
    args = sys.argv[1:] if argv is None else argv
    out_dir = Path(args[0]) if args else DEFAULT_DIR
    for path in export(out_dir):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
