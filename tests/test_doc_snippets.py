"""The Python snippets of README.md and docs/*.md that are marked ``<!-- test:run -->`` (on
the line before their fenced ``python`` block) run as written, from the repository's root,
each in a fresh interpreter; a snippet's ``# prints: TEXT`` comments say what it prints
(``<n>`` stands for a number), and the test checks that it does."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARKED = re.compile(r"<!-- test:run -->\s*\n```python\n(.*?)^```", re.S | re.M)


def snippets() -> list[tuple[str, str]]:
    out = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for i, code in enumerate(MARKED.findall(path.read_text())):
            out.append((f"{path.relative_to(ROOT)}#{i}", code))
    return out


def test_the_readme_has_a_marked_snippet():
    assert any(name.startswith("README.md") for name, _ in snippets())


@pytest.mark.slow
@pytest.mark.parametrize("name, code", snippets(), ids=[n for n, _ in snippets()])
def test_snippet_runs(name, code):
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, f"{name} failed:\n{res.stderr[-3000:]}"
    expected = re.findall(r"#\s*prints:\s*(.+)$", code, re.M)
    assert expected, f"{name}: no '# prints:' comment says what it prints"
    for text in expected:
        pattern = re.escape(text.strip()).replace(re.escape("<n>"), r"[0-9.,]+")
        assert re.search(pattern, res.stdout), f"{name}: expected '{text.strip()}' in its output:\n{res.stdout}"
