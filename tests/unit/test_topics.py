"""The topic registry: unique names and keys, safe key filling, subscriber patterns."""

from __future__ import annotations

import re

import pytest
from pydantic import BaseModel

from schemas.topics import TOPICS, Topic, topic


def test_names_and_templates_are_unique() -> None:
    names = [t.name for t in TOPICS]
    templates = [t.template for t in TOPICS]
    assert len(set(names)) == len(names), names
    assert len(set(templates)) == len(templates), templates


def test_templates_are_distinct_after_wildcarding() -> None:
    """Two topics must not collapse to the same subscriber pattern (they would cross-talk)."""
    patterns = [t.pattern() for t in TOPICS]
    assert len(set(patterns)) == len(patterns), patterns


def test_every_template_is_namespaced_by_fleet() -> None:
    for t in TOPICS:
        assert t.template.startswith("mc/{fleet}/"), t.template
        assert "fleet" in t.fields


def test_every_topic_with_a_model_is_a_pydantic_model() -> None:
    for t in TOPICS:
        if t.model is None:
            assert t.rate_hz is None, f"{t.name}: a token has no rate"
            continue
        assert isinstance(t.model, type) and issubclass(t.model, BaseModel), t.name
        assert t.rate_hz is not None and t.rate_hz > 0, t.name
        assert t.description


def test_key_fills_every_placeholder() -> None:
    t = topic("prior_rx")
    assert t.fields == ("fleet", "dst", "src")
    assert t.key(fleet="run-1", dst="host_0", src="veh-2") == "mc/run-1/v2x/rx/host_0/veh-2/prior"
    assert topic("truth").key(fleet="f") == "mc/f/sim/truth"


def test_key_requires_all_placeholders() -> None:
    with pytest.raises(ValueError, match="needs"):
        topic("prior_rx").key(fleet="f", dst="host")


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a b", "x$", "veh.1", "a" * 65, "ü", "abc\n", "\nabc"])
def test_key_rejects_unsafe_chunks(bad: str) -> None:
    with pytest.raises(ValueError, match="not a valid key chunk"):
        topic("fused").key(fleet="f", hid=bad)
    with pytest.raises(ValueError, match="not a valid key chunk"):
        topic("fused").pattern(fleet=bad)


def test_pattern_gives_star_chunks() -> None:
    t = topic("prior_rx")
    assert t.pattern() == "mc/*/v2x/rx/*/*/prior"
    assert t.pattern(fleet="f", dst="host") == "mc/f/v2x/rx/host/*/prior"
    assert topic("health").pattern(fleet="f") == "mc/f/health/*/*"


def test_keys_match_their_patterns() -> None:
    for t in TOPICS:
        values = {f: f"{f}-1" for f in t.fields}
        key = t.key(**values)
        regex = "^" + re.escape(t.pattern()).replace(r"\*", "[^/]+") + "$"
        assert re.match(regex, key), (t.name, key)


def test_unknown_topic_names_the_known_ones() -> None:
    with pytest.raises(KeyError, match="fused"):
        topic("nope")


def test_topic_is_immutable() -> None:
    t = topic("fused")
    assert isinstance(t, Topic)
    with pytest.raises(AttributeError):
        t.name = "other"  # type: ignore[misc]


def test_parse_gives_a_keys_placeholders_and_refuses_what_key_would_not_make() -> None:
    rx = topic("prior_rx")
    assert rx.parse(rx.key(fleet="f", dst="host", src="cv1")) == {"fleet": "f", "dst": "host", "src": "cv1"}
    for t in TOPICS:
        values = {f: f"{f}-1" for f in t.fields}
        assert t.parse(t.key(**values)) == values, t.name
    tx = topic("prior_tx")
    for bad in ("mc/f/v2x/tx/cv1.x/prior", "mc/f/v2x/tx/cv1/raw", "mc/f/v2x/tx/cv1", "mc/f/v2x/tx/a/b/prior", ""):
        assert tx.parse(bad) is None, bad
