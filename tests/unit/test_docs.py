"""The documentation: its Python examples run, its links lead somewhere, its generated figures are current,
and nothing in the repository refers to files outside it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)\s]*)?\)")


def _blocks() -> list[tuple[str, int, str]]:
    out = []
    for doc in DOCS:
        for i, m in enumerate(PYTHON_BLOCK.finditer(doc.read_text())):
            out.append((doc.relative_to(REPO).as_posix(), i, m.group(1)))
    return out


BLOCKS = _blocks()


def test_the_docs_have_python_examples_and_they_compile() -> None:
    assert len(BLOCKS) >= 2, "docs/api.md's examples"
    for name, i, code in BLOCKS:
        compile(code, f"{name}[{i}]", "exec")


@pytest.mark.slow
@pytest.mark.parametrize(("name", "i", "code"), BLOCKS, ids=[f"{n}[{i}]" for n, i, _ in BLOCKS])
def test_a_python_example_of_the_docs_runs(tmp_path, name: str, i: int, code: str) -> None:
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
    )  # fmt: skip
    assert r.returncode == 0, f"{name}[{i}] failed:\n{r.stderr[-3000:]}"
    assert r.stdout.strip(), f"{name}[{i}] printed nothing"


def test_every_relative_link_of_the_docs_leads_to_a_file() -> None:
    missing = []
    for doc in DOCS:
        for m in LINK.finditer(doc.read_text()):
            target = m.group(1)
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (doc.parent / target).exists():
                missing.append(f"{doc.relative_to(REPO)} -> {target}")
    assert not missing, missing


def test_the_generated_figures_are_current() -> None:
    r = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "docs_figures.py"), "--check"],
        capture_output=True, text=True, timeout=120, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"},
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr


def test_nothing_refers_to_files_outside_the_repository() -> None:
    r = subprocess.run(
        ["git", "grep", "-n", "-I", "-E", r"\.\./shared|DESIGN\.md|ZENOH\.md", "--", ".", ":!tests/unit/test_docs.py"],
        cwd=REPO, capture_output=True, text=True,
    )  # fmt: skip
    if r.returncode == 128:
        pytest.skip(f"not a git checkout: {r.stderr.strip()}")
    assert r.stdout == "", r.stdout


def test_the_readme_fits_on_a_screen_or_two() -> None:
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 120, len(lines)
    assert "pip install -e . && mapc fleet up --duration 20" in "\n".join(lines)
    assert "pip install -e '.[test]' && pytest -m \"not slow\"" in "\n".join(lines)
