"""The mutation list (scripts/mutations.yaml) stays applicable as the code moves: each
entry's snippet occurs exactly once in its file, and the tests it names exist. (A stale
entry stops ``scripts/mutate.py``; this finds it in the suite, before a mutation run.)"""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_every_mutation_applies_once_and_names_existing_tests():
    entries = yaml.safe_load((ROOT / "scripts" / "mutations.yaml").read_text())
    assert len(entries) > 50
    stale = []
    for m in entries:
        path = ROOT / m["file"]
        count = path.read_text().count(m["original"]) if path.is_file() else -1
        if count != 1:
            stale.append(f"{m['id']}: its snippet occurs {count} times in {m['file']}")
        files = [t.split("::")[0] for t in str(m["tests"]).split() if t.startswith("tests/")]
        stale += [f"{m['id']}: no test file {f}" for f in files if not (ROOT / f).is_file()]
    assert not stale, "; ".join(stale)
