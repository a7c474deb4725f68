"""Regenerate the figures of README.md and docs/*.md from the commands shown beside them.

Every figure in the documentation sits between two markers::

    <!-- figure NAME: python scripts/docs_figures.py NAME -->
    ...generated, do not edit...
    <!-- /figure -->

and is rewritten here from the command it names, so it cannot go stale:

    python scripts/docs_figures.py             # every figure (runs a 20 s fleet: about a minute or two)
    python scripts/docs_figures.py topics      # one figure
    python scripts/docs_figures.py --check     # exit 1 if a deterministic figure is out of date (a test runs this)

Figures measured on a live fleet (``first-run``) depend on the machine: the block says when, on how many
cores and at what load it was made. ``first-run`` also writes ``docs/birdseye.png`` (the run's picture);
``view`` writes ``docs/view.png`` (``mapc view`` in headless Chromium: the view and browser extras and
Debian's chromium).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
MARK = re.compile(r"(<!-- figure (?P<name>[a-z0-9-]+): [^\n]*-->\n)(?P<body>.*?)(<!-- /figure -->)", re.S)


@dataclass(frozen=True)
class Figure:
    make: Callable[[], str]  # the Markdown between the markers
    deterministic: bool  # --check compares it (a live run's figures are not)


def _machine() -> str:
    load1 = os.getloadavg()[0]
    return f"Run on {time.strftime('%Y-%m-%d')}: {os.cpu_count()} cores, load average {load1:.1f} when it started"


def first_run() -> str:
    """`mapc fleet up --duration 20` as a user runs it: its closing table, and its bird's-eye picture."""
    machine = _machine()
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": str(REPO), "MAPC_RUNS_DIR": str(Path(tmp) / "runs")}
        cmd = [sys.executable, "-m", "services.cli", "fleet", "up", "--duration", "20", "--no-summary"]
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp, timeout=600, check=True).stdout
        (png,) = (Path(tmp) / "runs").glob("*/birdseye.png")
        shutil.copyfile(png, REPO / "docs" / "birdseye.png")
    lines = out.rstrip().splitlines()
    start = max(i for i, line in enumerate(lines) if line.startswith("fleet local:"))
    table = "\n".join(lines[start:])
    table = re.sub(r"\S*runs/local-\d{8}-\d{6}", "runs/local-<date>-<time>", table)
    return f"```console\n$ mapc fleet up --duration 20\n...\n{table}\n```\n({machine}.)\n"


def view() -> str:
    """`mapc view` of a recorded default fleet in headless Chromium (the view and browser extras, Debian's
    chromium): a 10 s recording, the viewer started on it, a screenshot once the scene has drawn."""
    import socket

    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("view: needs Debian's chromium (apt-get install chromium) and the browser extra")
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": str(REPO), "MAPC_RUNS_DIR": str(Path(tmp) / "runs")}
        cli = [sys.executable, "-m", "services.cli"]
        fleet = [*cli, "fleet", "up", "--duration", "10", "--record", "--no-summary", "--fleet", "docsview"]
        subprocess.run(fleet, capture_output=True, text=True, env=env, cwd=tmp, timeout=600, check=True)
        (rec,) = (Path(tmp) / "runs").glob("*/recording.mcap")
        ports = []
        for _ in range(2):
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                ports.append(sock.getsockname()[1])
        argv = [*cli, "view", "--file", str(rec), "--web-port", str(ports[0]), "--grpc-port", str(ports[1])]
        log = Path(tmp) / "view.log"
        with log.open("w") as out:
            proc = subprocess.Popen([*argv, "--exit-after", "300"], stdout=out, stderr=subprocess.STDOUT, env=env)
        try:
            url = None
            for _ in range(600):
                url = next(
                    (x.split("open ", 1)[1].split()[0] for x in log.read_text().splitlines() if "open http" in x), None
                )
                if url or proc.poll() is not None:
                    break
                time.sleep(0.1)
            if url is None:
                raise SystemExit(f"view: the viewer did not start:\n{log.read_text()[-2000:]}")
            with sync_playwright() as p:
                args = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
                browser = p.chromium.launch(executable_path=chromium, args=args)
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(url)
                time.sleep(30.0)  # Rerun's web viewer loads and draws in about 20 s (WebGL in software here)
                page.screenshot(path=str(REPO / "docs" / "view.png"))
                browser.close()
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    return "![mapc view of a recorded default fleet](view.png)\n"


def topics() -> str:
    """The topic registry (schemas/topics.py) as a table."""
    from schemas.topics import TOPICS

    rows = ["| topic | key expression | message | rate | what |", "|---|---|---|---|---|"]
    for t in TOPICS:
        model = f"`{t.model.__name__}`" if t.model is not None else "liveliness token"
        rate = f"{t.rate_hz:g} Hz" if t.rate_hz else "-"
        rows.append(f"| `{t.name}` | `{t.template}` | {model} | {rate} | {t.description} |")
    return "\n".join(rows) + "\n"


FIGURES: dict[str, Figure] = {
    "first-run": Figure(first_run, deterministic=False),
    "topics": Figure(topics, deterministic=True),
    "view": Figure(view, deterministic=False),
}


def blocks(text: str) -> list[re.Match]:
    return list(MARK.finditer(text))


def rewrite(names: set[str], check: bool) -> list[str]:
    """Rewrite the figures ``names`` in every document (or, with ``check``, list the stale ones)."""
    made = {n: FIGURES[n].make() for n in sorted(names)}
    stale = []
    for doc in DOCS:
        text = doc.read_text()
        new = MARK.sub(lambda m: m.group(1) + made.get(m.group("name"), m.group("body")) + m.group(4), text)
        for m in blocks(text):
            if m.group("name") not in FIGURES:
                raise SystemExit(f"{doc.relative_to(REPO)}: unknown figure {m.group('name')!r}")
        if new != text:
            stale.append(str(doc.relative_to(REPO)))
            if not check:
                doc.write_text(new)
    return stale


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("names", nargs="*", help=f"figures to make (default all): {', '.join(FIGURES)}")
    p.add_argument("--check", action="store_true", help="only say whether the deterministic figures are current")
    a = p.parse_args(argv)
    unknown = set(a.names) - FIGURES.keys()
    if unknown:
        p.error(f"unknown figures {sorted(unknown)}; known: {', '.join(FIGURES)}")
    names = set(a.names) or set(FIGURES)
    if a.check:
        names = {n for n in names if FIGURES[n].deterministic}
    stale = rewrite(names, a.check)
    verb = "out of date" if a.check else "rewritten"
    print(f"{verb}: {', '.join(stale) or 'none'}")
    return 1 if a.check and stale else 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main())
