"""Shared memory a fleet leaves behind: Zenoh's ``*.zenoh`` segments and the POSIX semaphores of
``multiprocessing`` queues (``sem.mp-*``) in /dev/shm. A process that exits cleanly removes its own; a
killed one (SIGKILL, a crash) cannot, and its segments stay until the machine restarts.

The launcher notes which segments its processes map (:func:`mapped`, from ``/proc/<pid>/maps``, while they
run) in ``state.json``; when the fleet is down (``mapc fleet down``, the end of a run) :func:`release`
removes those that no live process maps any more.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

__all__ = ["SHM_DIR", "mapped", "release"]

SHM_DIR = Path("/dev/shm")


def _maps(pid: int, root: Path) -> set[str]:
    """Paths under ``root`` that process ``pid`` maps (empty when it is gone or not ours to read)."""
    try:
        text = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    prefix = f"{root}/"
    out = set()
    for line in text.splitlines():
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and parts[5].startswith(prefix) and not parts[5].endswith("(deleted)"):
            out.add(parts[5])
    return out


def _group(pgids: set[int]) -> list[int]:
    """Pids of the processes in these process groups (a service and the workers it started)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[2]) in pgids:
                    out.append(int(d.name))
            except (OSError, IndexError, ValueError):
                continue
    return out


def mapped(pgids: Iterable[int], pids: Iterable[int] = (), root: Path = SHM_DIR) -> set[str]:
    """The files under ``root`` mapped now by the processes of these process groups and by ``pids``."""
    return set().union(*(_maps(pid, root) for pid in {*_group(set(pgids)), *pids}))


def release(segments: Iterable[str], root: Path = SHM_DIR) -> list[str]:
    """Remove those of ``segments`` (paths under ``root``) that no live process maps; the removed ones."""
    wanted = {s for s in segments if str(s).startswith(f"{root}/") and os.path.exists(s)}
    if not wanted:
        return []
    in_use = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            in_use |= _maps(int(d.name), root) & wanted
    removed = []
    for s in sorted(wanted - in_use):
        try:
            os.unlink(s)
            removed.append(s)
        except OSError:
            continue
    return removed
