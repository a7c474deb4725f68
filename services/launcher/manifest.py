"""Fleet manifests: the process topology as data (``manifests/fleet.yaml`` beside this file), resolved into
command lines.

A manifest lists process templates (module, role, id, arguments, start order, restart policy).
``resolve`` fills the templates' ``{placeholders}`` from the fleet parameters and expands
``for_each: vehicle`` templates once per connected vehicle; the result can be printed before
anything runs (``mapc fleet up --dry-run``).

Arguments are strings, or ``[flag, value]`` pairs that are left out when the value's placeholder
is None (e.g. ``["--duration", "{duration_s}"]`` without a duration).
"""

from __future__ import annotations

import string
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mapcontainer.config import ConfigError, find_preset, read_yaml, validate_model

__all__ = [
    "DEFAULT_MANIFEST",
    "FleetParams",
    "Manifest",
    "ProcessSpec",
    "ProcessTemplate",
    "RestartPolicy",
    "load_manifest",
    "keys_dir",
    "manifest_path",
    "resolve",
    "vehicle_ids",
]

MANIFEST_DIR = Path(__file__).resolve().parent / "manifests"  # package data: fleet, fleet-host-a, fleet-host-b
DEFAULT_MANIFEST = "fleet"
NAME = r"^[A-Za-z0-9_\-]{1,64}$"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RestartPolicy(_Strict):
    """When and how soon a process that exited is started again.

    on-failure: restart after a non-zero exit or a signal; always: after any exit; never.
    The n-th consecutive restart waits min(backoff_max_s, backoff_initial_s * backoff_factor**(n-1));
    a process that ran ``reset_after_s`` without exiting starts again from the initial backoff.
    """

    policy: Literal["on-failure", "always", "never"] = "on-failure"
    backoff_initial_s: float = Field(0.5, ge=0)
    backoff_factor: float = Field(2.0, ge=1)
    backoff_max_s: float = Field(10.0, ge=0)
    reset_after_s: float = Field(30.0, gt=0)
    max_restarts: int | None = Field(20, ge=0, description="give up after this many restarts (None: never)")

    def delay_s(self, consecutive: int) -> float:
        """Backoff before the ``consecutive``-th restart in a row (1, 2, ...)."""
        if consecutive < 1:
            raise ValueError(f"consecutive must be >= 1, got {consecutive}")
        return min(self.backoff_max_s, self.backoff_initial_s * self.backoff_factor ** (consecutive - 1))

    def wants_restart(self, returncode: int, restarts: int) -> bool:
        if self.policy == "never" or (self.max_restarts is not None and restarts >= self.max_restarts):
            return False
        return self.policy == "always" or returncode != 0


class FleetParams(_Strict):
    """What a fleet run varies: the ``mapc fleet up`` options."""

    fleet: str = Field("local", pattern=NAME)
    scenario: str = "paper-urban"
    vehicles: int | None = Field(None, ge=1, description="None: as many as the scenario defines")
    network: str = "dsrc"
    mode: Literal["distributed", "centralized"] = "distributed"
    duration_s: float | None = Field(None, gt=0, description="scenario seconds; None: until stopped")
    seed: int = Field(0, ge=0)
    time_scale: float | Literal["auto"] = Field(
        "auto",
        description="scenario seconds per wall second; auto: as fast as real time, the world's clock pausing "
        "while a vehicle or the host it needs is still on the previous frame (every frame is processed)",
    )

    @field_validator("time_scale")
    @classmethod
    def _scale_in_range(cls, v):
        if v != "auto" and not 1e-3 <= v <= 100.0:
            raise ValueError(f"time_scale must be auto or in [0.001, 100], got {v}")
        return v

    @property
    def clock_scale(self) -> float:
        """The slope of the world's clock that the other services convert wall time with (auto: 1, with pauses)."""
        return 1.0 if self.time_scale == "auto" else float(self.time_scale)

    host_id: str = Field("host", pattern=NAME)
    ego: str = Field("cv0", pattern=NAME, description="the vehicle the host container runs on")
    standby: bool = Field(False, description="run a warm standby host that takes over when the host is gone")
    record: bool = Field(False, description="record every message of the fleet to {run_dir}/recording.mcap")
    downlink: bool = Field(
        False, description="the host sends every vehicle what the others know about its pose (host --downlink)"
    )
    signing: bool = Field(True, description="vehicles sign their V2X messages, the host accepts signed ones only")
    keys: str | None = Field(
        None, description="the fleet's keys directory (mapc keys init); None: a test CA made for the run"
    )
    zenoh_config: str | None = Field(None, description="a Zenoh JSON5 file every process starts from")
    insecure: bool = Field(
        False, description="the open peer mesh: no Zenoh login, no access control (debugging; mesh.py)"
    )


class ProcessTemplate(_Strict):
    name: str
    module: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_.]*$")
    role: str = Field(pattern=NAME)
    id: str
    args: list[str | list[str]] = Field(default_factory=list)
    for_each: Literal["vehicle"] | None = None
    when: str | None = Field(None, description="a boolean fleet parameter: the process runs only when it is true")
    start_order: int = 0
    restart: RestartPolicy | None = None
    ready_timeout_s: float = Field(90.0, gt=0, description="until its liveliness token is seen")
    stop_timeout_s: float = Field(8.0, gt=0, description="after SIGINT, before SIGKILL")

    @model_validator(mode="after")
    def _pairs(self) -> ProcessTemplate:
        for a in self.args:
            if isinstance(a, list) and len(a) != 2:
                raise ValueError(f"{self.name}: an argument pair must be [flag, value], got {a}")
        return self


class Manifest(_Strict):
    name: str
    description: str = ""
    defaults: FleetParams = FleetParams()
    common_args: list[str | list[str]] = Field(default_factory=list, description="appended to every process")
    restart: RestartPolicy = RestartPolicy()
    processes: list[ProcessTemplate] = Field(min_length=1)


@dataclass(frozen=True)
class ProcessSpec:
    """One process to run: resolved command line and supervision settings."""

    name: str
    module: str
    role: str
    id: str
    argv: list[str]
    start_order: int
    restart: RestartPolicy
    ready_timeout_s: float
    stop_timeout_s: float
    env: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "module": self.module,
            "role": self.role,
            "id": self.id,
            "argv": self.argv,
            "start_order": self.start_order,
            "restart": self.restart.model_dump(),
            "ready_timeout_s": self.ready_timeout_s,
            "stop_timeout_s": self.stop_timeout_s,
        }


def manifest_path(name_or_path: str | Path | None = None) -> Path:
    """A manifest by name (``fleet``, ``fleet-host-a``, ...: the built-in ones or ``manifests/NAME.yaml`` in
    a user config directory, see :func:`mapcontainer.config.user_config_dirs`) or a YAML file by path."""
    text = str(name_or_path or DEFAULT_MANIFEST)
    if Path(text).suffix:
        if not Path(text).exists():
            raise ConfigError(f"fleet manifest {text} does not exist")
        return Path(text).resolve()
    return find_preset("manifests", text, "fleet manifest", builtin=MANIFEST_DIR)


def load_manifest(name_or_path: str | Path | None = None) -> Manifest:
    p = manifest_path(name_or_path)
    return validate_model(Manifest, read_yaml(p), p)


def keys_dir(params: FleetParams, run_dir: str | Path) -> str | None:
    """Where the fleet's keys are: the given directory, the run's own (``keys/``), or None (unsigned)."""
    if not params.signing:
        return None
    return params.keys or str(Path(run_dir) / "keys")


def vehicle_ids(params: FleetParams) -> list[str]:
    """The connected vehicles' ids, as the world names them (cv0, cv1, ...)."""
    n = params.vehicles
    if n is None:
        from mapcontainer.sim.config import load_scenario

        n = load_scenario(params.scenario).n_connected
    return [f"cv{i}" for i in range(n)]


class _Missing:
    """Formats as itself, so that an argument pair with a None value can be recognised and left out."""

    def __format__(self, spec: str) -> str:
        return "\x00none\x00"


def _fill(template: str, values: dict[str, Any]) -> str:
    names = {f for _, f, _, _ in string.Formatter().parse(template) if f}
    unknown = names - values.keys()
    if unknown:
        raise ConfigError(f"unknown placeholder(s) {sorted(unknown)} in {template!r}; known: {sorted(values)}")
    return template.format(**{k: (_Missing() if v is None else v) for k, v in values.items()})


def _args(items: list[str | list[str]], values: dict[str, Any]) -> list[str]:
    out: list[str] = []
    for a in items:
        if isinstance(a, list):
            flag, val = _fill(a[0], values), _fill(a[1], values)
            if "\x00none\x00" not in val:
                out += [flag, val]
        else:
            val = _fill(a, values)
            if "\x00none\x00" in val:
                raise ConfigError(f"argument {a!r} has no value; write it as a [flag, value] pair to make it optional")
            out.append(val)
    return out


def resolve(
    manifest: Manifest,
    params: FleetParams,
    run_dir: str | Path,
    connect: str,
    python: str = sys.executable,
    logins: str | Path | None = None,
) -> list[ProcessSpec]:
    """Every process of the fleet, in start order (stable within an order). ``logins``: the directory of
    the processes' Zenoh logins (``NAME.json5``, services.launcher.mesh), each process's ``{zenoh_config}``."""
    vids = vehicle_ids(params)
    base = {
        **params.model_dump(),
        "keys_dir": keys_dir(params, run_dir),
        "run_dir": str(run_dir),
        "connect": connect,
        "vehicle_ids": ",".join(vids),
        "clock_scale": params.clock_scale,
        "downlink_flag": "--downlink" if params.downlink else "--no-downlink",
        "python": python,
    }
    specs: list[ProcessSpec] = []
    for tpl in manifest.processes:
        if tpl.when is not None:
            if not isinstance(base.get(tpl.when), bool):
                raise ConfigError(f"{tpl.name}: when: {tpl.when!r} is not a boolean fleet parameter")
            if not base[tpl.when]:
                continue
        instances = [{"vid": v} for v in vids] if tpl.for_each == "vehicle" else [{}]
        for extra in instances:
            values = {**base, **extra}
            sid = _fill(tpl.id, values)
            values["id"] = sid
            name = _fill(tpl.name, values)
            if logins is not None:
                values["zenoh_config"] = str(Path(logins) / f"{name}.json5")
            argv = [python, "-m", tpl.module, *_args(tpl.args, values), *_args(manifest.common_args, values)]
            specs.append(
                ProcessSpec(
                    name=name,
                    module=tpl.module,
                    role=tpl.role,
                    id=sid,
                    argv=argv,
                    start_order=tpl.start_order,
                    restart=tpl.restart or manifest.restart,
                    ready_timeout_s=tpl.ready_timeout_s,
                    stop_timeout_s=tpl.stop_timeout_s,
                )
            )
    names = [s.name for s in specs]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(f"process names must be unique; repeated: {sorted(dup)}")
    keys = [(s.role, s.id) for s in specs]
    dup_k = {k for k in keys if keys.count(k) > 1}
    if dup_k:
        raise ConfigError(f"(role, id) must be unique (one liveliness token each); repeated: {sorted(dup_k)}")
    return sorted(specs, key=lambda s: s.start_order)
