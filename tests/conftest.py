"""Every test session has its own fleet registry, so tests never see (or stop) the user's fleets."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def _own_fleet_registry(tmp_path_factory):
    old = os.environ.get("MAPC_STATE_DIR")
    os.environ["MAPC_STATE_DIR"] = str(tmp_path_factory.mktemp("mapc-state"))  # inherited by subprocesses
    yield
    if old is None:
        os.environ.pop("MAPC_STATE_DIR", None)
    else:
        os.environ["MAPC_STATE_DIR"] = old
