"""The exported JSON Schema files (schemas/json/) are current and describe the wire format."""

from __future__ import annotations

import json
from pathlib import Path

from schemas.export import DEFAULT_DIR, MODELS, export, render, schema_filename, stale
from schemas.models import SecuredMessage
from schemas.topics import TOPICS


def test_committed_schema_files_are_current() -> None:
    bad = stale(DEFAULT_DIR)
    assert bad == [], (
        f"schemas/json is stale ({', '.join(bad)}): run `mapc schemas export` (or python -m schemas.export)"
    )


def test_export_writes_one_file_per_model_plus_topics(tmp_path: Path) -> None:
    written = export(tmp_path)
    names = sorted(p.name for p in written)
    assert names == sorted(
        [
            "sensor_frame.json",
            "raw_observations.json",
            "vehicle_prior.json",
            "pose_downlink.json",
            "fused_state.json",
            "ground_truth.json",
            "health_status.json",
            "eval_metrics.json",
            "secured_message.json",
            "topics.json",
        ]
    )
    assert stale(tmp_path) == []
    for path in written:
        text = path.read_text(encoding="utf-8")
        assert text.endswith("}\n")
        assert text == json.dumps(json.loads(text), sort_keys=True, indent=2) + "\n"


def test_export_is_deterministic(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    export(a)
    export(b)
    for name in render():
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_stale_reports_missing_and_changed_files(tmp_path: Path) -> None:
    assert sorted(stale(tmp_path)) == sorted(render())
    export(tmp_path)
    (tmp_path / "fused_state.json").write_text("{}\n", encoding="utf-8")
    (tmp_path / "topics.json").unlink()
    assert sorted(stale(tmp_path)) == ["fused_state.json", "topics.json"]


def test_every_topic_model_is_exported() -> None:
    assert {t.model for t in TOPICS if t.model is not None} | {SecuredMessage} == set(MODELS)
    assert {schema_filename(m) for m in MODELS} | {"topics.json"} == set(render())


def test_array_fields_document_dtype_and_shape() -> None:
    schema = json.loads(render()["fused_state.json"])
    assert schema["title"] == "FusedState"
    cov = schema["properties"]["object_cov"]
    assert cov["x-dtype"] == "float32" and cov["x-shape"] == ["N", 6]
    assert "little-endian" in cov["description"]
    objects = json.loads(render()["vehicle_prior.json"])["$defs"]["ObjectObservations"]["properties"]
    assert objects["p_body_cm"]["x-dtype"] == "int16"
    assert objects["cov"]["x-covariance"] == 3 and objects["cov"]["x-correlation-dtype"] == "int8"
    pose_cov = json.loads(render()["vehicle_prior.json"])["properties"]["pose_cov"]
    assert pose_cov["x-bytes-per-matrix"] == 42 and pose_cov["x-correlation-dtype"] == "int16"


def test_topics_json_lists_the_registry() -> None:
    doc = json.loads(render()["topics.json"])
    assert [t["name"] for t in doc["topics"]] == [t.name for t in TOPICS]
    fused = next(t for t in doc["topics"] if t["name"] == "fused")
    assert fused == {
        "name": "fused",
        "key": "mc/{fleet}/host/{hid}/fused",
        "model": "FusedState",
        "rate_hz": 10.0,
        "description": fused["description"],
    }
    alive = next(t for t in doc["topics"] if t["name"] == "alive")
    assert alive["model"] is None and alive["rate_hz"] is None


def test_every_property_carries_its_wire_tag() -> None:
    from schemas.tags import TAGS

    for name, text in render().items():
        if name == "topics.json":
            continue
        schema = json.loads(text)
        assert "x-tag" in schema["$comment"]
        for node in [schema, *schema.get("$defs", {}).values()]:
            for field, prop in node.get("properties", {}).items():
                assert prop["x-tag"] == TAGS[field], f"{name}: {field}"
    prior = json.loads(render()["vehicle_prior.json"])
    assert prior["properties"]["schema_version"]["x-tag"] == 0
    assert prior["$defs"]["ObjectObservations"]["properties"]["cov"]["x-tag"] == 17
