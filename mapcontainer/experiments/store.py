"""Finished tasks on disk, so that an interrupted experiment resumes where it stopped.

``OUT/tasks/`` holds ``settings.json`` (the experiment's name, its settings and their hash), one
``<key>.json`` per finished task (written whole or not at all: a temporary file renamed into place) and
``failed/<key>.txt`` per task that raised (its description and traceback; removed when it succeeds on
a rerun). A task's key is a hash of the function and its arguments, seed included, so the same command
finds the same files. Opening a directory whose settings hash differs refuses (``SettingsChanged``):
results of two configurations are never mixed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

__all__ = ["SettingsChanged", "TaskStore", "digest"]

FORMAT = 1  # the layout of a task file; part of the settings hash


class SettingsChanged(ValueError):
    """The output directory holds tasks of another configuration."""


def digest(obj: Any) -> str:
    """A stable hash of JSON-able ``obj`` (sorted keys; tuples as lists)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class TaskStore:
    """The finished tasks of one experiment in ``out_dir/tasks``; ``fresh`` deletes earlier ones first."""

    def __init__(self, out_dir: str | Path, experiment: str, settings: dict, fresh: bool = False):
        self.dir = Path(out_dir) / "tasks"
        self.hash = digest({"experiment": experiment, "settings": settings, "format": FORMAT})
        if fresh and self.dir.exists():
            shutil.rmtree(self.dir)
        meta = self.dir / "settings.json"
        if meta.exists():
            old = json.loads(meta.read_text())
            if old.get("hash") != self.hash:
                was = old.get("settings", {})
                changed = sorted(k for k in set(was) | set(settings) if digest(was.get(k)) != digest(settings.get(k)))
                raise SettingsChanged(
                    f"{self.dir} holds tasks of {old.get('experiment')} with other settings "
                    f"({', '.join(changed) or 'the task format'} differ): use another output directory, "
                    "or --fresh to delete them"
                )
        else:
            (self.dir / "failed").mkdir(parents=True, exist_ok=True)
            body = {"experiment": experiment, "hash": self.hash, "settings": settings, "format": FORMAT}
            _write(meta, json.dumps(body, indent=1, sort_keys=True, default=str) + "\n")

    def load(self, keys: list[str]) -> dict[str, dict]:
        """The stored records of those ``keys`` that are done: {"result": ..., "timing": {...}}."""
        out = {}
        for k in keys:
            p = self.dir / f"{k}.json"
            if p.exists():
                out[k] = json.loads(p.read_text())
        return out

    def save(self, key: str, timing: dict, result_json: str) -> None:
        """A finished task: its timing and its result (as JSON text, stored verbatim)."""
        _write(self.dir / f"{key}.json", f'{{"timing": {json.dumps(timing)}, "result": {result_json}}}\n')
        (self.dir / "failed" / f"{key}.txt").unlink(missing_ok=True)

    def fail(self, key: str, text: str) -> Path:
        """A task that raised: its description and traceback, for a person to read."""
        path = self.dir / "failed" / f"{key}.txt"
        path.parent.mkdir(parents=True, exist_ok=True)
        _write(path, text)
        return path
