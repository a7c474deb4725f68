"""Presets ship with the package and a user's own directories override them, first match wins."""

from __future__ import annotations

import shutil

import pytest

from mapcontainer.channel import list_profiles, load_profile
from mapcontainer.cli import build_parser, run
from mapcontainer.config import BUILTIN_DIR, ConfigError, list_presets, preset_dirs
from mapcontainer.sim.config import list_scenarios, load_scenario
from services.launcher.manifest import MANIFEST_DIR, load_manifest, manifest_path


def test_builtin_presets_are_package_data() -> None:
    assert BUILTIN_DIR.parent.name == "mapcontainer"
    assert set(list_presets("scenarios")) >= {"paper-urban", "overlap"}
    assert all(p.is_relative_to(BUILTIN_DIR) for p in list_presets("network").values())
    assert manifest_path() == MANIFEST_DIR / "fleet.yaml"
    assert load_manifest("fleet-host-a").name != load_manifest("fleet-host-b").name


def test_config_dir_overrides_and_adds(tmp_path, monkeypatch) -> None:
    own = tmp_path / "mine"
    (own / "scenarios").mkdir(parents=True)
    shutil.copy(BUILTIN_DIR / "scenarios" / "overlap.yaml", own / "scenarios" / "my-street.yaml")
    text = (BUILTIN_DIR / "network" / "dsrc.yaml").read_text().replace("latency_ms: 18.0", "latency_ms: 35.0")
    assert text != (BUILTIN_DIR / "network" / "dsrc.yaml").read_text(), "the preset's latency line changed"
    (own / "network").mkdir()
    (own / "network" / "dsrc.yaml").write_text(text)
    monkeypatch.setenv("MAPC_CONFIG_DIR", str(own))
    assert preset_dirs("network")[0] == own / "network"
    assert "my-street" in list_scenarios() and "paper-urban" in list_scenarios()
    assert load_scenario("my-street") == load_scenario("overlap")
    assert load_profile("dsrc").latency_ms == 35.0, "the user's preset wins"
    assert load_profile("ideal").latency_ms == 0.0, "the others stay built in"
    assert list_profiles().count("dsrc") == 1


def test_xdg_user_directory_is_searched_after_config_dir(tmp_path, monkeypatch) -> None:
    xdg = tmp_path / "xdg"
    (xdg / "mapcontainer" / "manifests").mkdir(parents=True)
    shutil.copy(MANIFEST_DIR / "fleet.yaml", xdg / "mapcontainer" / "manifests" / "mine.yaml")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(xdg))
    assert manifest_path("mine") == xdg / "mapcontainer" / "manifests" / "mine.yaml"
    with pytest.raises(ConfigError, match="unknown fleet manifest 'nope'; presets: fleet, fleet-host-a"):
        manifest_path("nope")


def test_missing_config_dir_is_a_configuration_error(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("MAPC_CONFIG_DIR", str(tmp_path / "absent"))
    with pytest.raises(ConfigError, match="does not exist"):
        list_scenarios()
    assert run(build_parser(), ["scenario", "list"]) == 2
    assert "absent" in capsys.readouterr().err


def test_config_dir_option_lists_the_users_presets(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.delenv("MAPC_CONFIG_DIR", raising=False)
    (tmp_path / "scenarios").mkdir()
    shutil.copy(BUILTIN_DIR / "scenarios" / "overlap.yaml", tmp_path / "scenarios" / "corner.yaml")
    assert run(build_parser(), ["--config-dir", str(tmp_path), "scenario", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    corner = next(line for line in lines if line.startswith("corner"))
    assert str(tmp_path / "scenarios" / "corner.yaml") in corner
    assert not any(str(BUILTIN_DIR) in line for line in lines), "built-in presets are listed without a path"
