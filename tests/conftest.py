"""Every test session has its own fleet registry, so tests never see (or stop) the user's fleets, and
sees only the built-in presets (no user config directory)."""

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


@pytest.fixture(scope="session", autouse=True)
def _builtin_presets_only(tmp_path_factory):
    old = {k: os.environ.get(k) for k in ("MAPC_CONFIG_DIR", "XDG_CONFIG_HOME")}
    os.environ.pop("MAPC_CONFIG_DIR", None)
    os.environ["XDG_CONFIG_HOME"] = str(tmp_path_factory.mktemp("xdg-config"))  # empty: no user presets
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def dask_cluster():
    """The runner's Dask LocalCluster of 2 worker processes (the cluster extra): executors.local_cluster."""
    pytest.importorskip("distributed")
    from mapcontainer.experiments.executors import local_cluster

    with local_cluster(2) as cluster:
        yield cluster
