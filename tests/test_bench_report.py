"""scripts/bench.py's report splicing: a rerun of some sections keeps the others and says
where, when and on which machine they were measured."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_script", ROOT / "scripts" / "bench.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module          # its dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def _report(date: str, machine: str, code: str, sections: dict[str, str], note: str | None = None) -> list[str]:
    lines = ["# Benchmarks", "", "| | |", "|---|---|", f"| date | {date} |", f"| machine | {machine} |",
             f"| code | {code} |", ""]
    if note:
        lines += [note, ""]
    lines += ["## Summary", ""] + [f"- {text} ({s})." for s, text in sections.items()] + [""]
    for s, text in sections.items():
        lines += [f"## ({s}) Section {s}", "", text, ""]
    return lines


def test_a_spliced_report_names_the_machine_and_the_history_of_its_kept_sections():
    bench = _bench()
    first = _report("day 1", "slow CPU (family 23)", "git aaa", {"a": "A1", "e": "E1", "i": "I1"})
    second = bench.splice_sections(first, _report("day 2", "fast CPU (family 26)", "git bbb", {"i": "I2"}), ["i"])
    text = "\n".join(second)
    assert "| machine | fast CPU (family 26) |" in text
    assert "kept from the earlier file (day 1, git aaa, on slow CPU (family 23))" in text
    assert "A1" in text and "E1" in text and "I2" in text and "I1" not in text
    # a second splice keeps the first one's note, so section a is still traced to day 1
    third = bench.splice_sections(second, _report("day 3", "fast CPU (family 26)", "git ccc", {"e": "E3"}), ["e"])
    text = "\n".join(third)
    assert "kept from the earlier file (day 2, git bbb, on fast CPU (family 26))" in text
    assert "That file's own note: Sections i are from this run" in text and "(day 1, git aaa, on slow CPU" in text
    assert "A1" in text and "E3" in text and "I2" in text and "E1" not in text
