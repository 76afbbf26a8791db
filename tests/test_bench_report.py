"""The benchmark report (mysim_jax/bench/report.py): its header, its summary from a section's
results, its sections split apart, and a rerun of some sections spliced into an earlier
report, which keeps the others and says where, when and on which machine they were measured."""

from __future__ import annotations

from types import SimpleNamespace

from mysim_jax.bench import report
from mysim_jax.bench.accuracy_cases import AccuracyRow, Method
from mysim_jax.bench.timing import ThroughputRow


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
    first = _report("day 1", "slow CPU (family 23)", "git aaa", {"a": "A1", "e": "E1", "i": "I1"})
    second = report.splice_sections(first, _report("day 2", "fast CPU (family 26)", "git bbb", {"i": "I2"}), ["i"])
    text = "\n".join(second)
    assert "| machine | fast CPU (family 26) |" in text
    assert "kept from the earlier file (day 1, git aaa, on slow CPU (family 23))" in text
    assert "A1" in text and "E1" in text and "I2" in text and "I1" not in text
    # a second splice keeps the first one's note, so section a is still traced to day 1
    third = report.splice_sections(second, _report("day 3", "fast CPU (family 26)", "git ccc", {"e": "E3"}), ["e"])
    text = "\n".join(third)
    assert "kept from the earlier file (day 2, git bbb, on fast CPU (family 26))" in text
    assert "That file's own note: Sections i are from this run" in text and "(day 1, git aaa, on slow CPU" in text
    assert "A1" in text and "E3" in text and "I2" in text and "E1" not in text


def test_split_sections_separates_header_summary_and_lettered_sections():
    header, summary, sections = report.split_sections(_report("d", "m", "git c", {"b": "B", "f": "F"}))
    assert header[0] == "# Benchmarks" and "| code | git c |" in header
    assert [ln for ln in summary if ln] == ["- B (b).", "- F (f)."]
    assert list(sections) == ["b", "f"]
    assert sections["f"][0] == "## (f) Section f" and "F" in sections["f"]


def test_summary_lines_judge_the_targets_and_name_their_sections():
    rope = [AccuracyRow("rope_net", Method("rk4", "dt = 1e-04", (), "float64", step=1e-4), "ok", 2e-9, 0.5),
            AccuracyRow("rope_net", Method("tsit5", "rtol = 1e-08", (), "float64"), "failed: x")]
    results = {
        "ours_4096": 2.5e6, "kernel_ratio": {1024: 0.9, 4096: 0.7}, "kernel_met": False,
        "b": {1: {"matmul": 1000.0, "segment_sum": 2000.0}},
        "env_rows": [ThroughputRow("4096", 4096, 1, [2.0], 1.0, 1.0)], "env_rate_level": (25.0, "full"),
        "d": rope, "g": {"iteration": 50.0, "env": 200.0},
        "f": {"library": 3.0e6, "floor": 9.0e6},
        "k": {"whole image": 1.4, "region": 23.5, "region, first stage only": 60.0},
        "levels": {"full": {"rate": {256: 900.0, 1024: 1200.0}}, "train": {"rate": {1024: 9000.0}}},
    }
    lines = report.summary_lines(results)
    assert lines[:2] == ["## Summary", ""] and lines[-1] == ""
    text = "\n".join(lines)
    assert "**2,500,000 env-steps/s** — target ≥ 1,000,000: **met**" in text
    assert "B=1024: **0.90×**, B=4096: **0.70×**" in text and "**NOT met**." in text
    assert "**2,048.0 team steps/s** at 25 Hz on the level `full` (where the time goes: (e); the levels' targets: (i))" in text
    assert ("- Fidelity levels (i), B = 1024, 10 Hz: `full` 1,200 team steps/s, target ≥ 1,000: met; "
            "`train` 9,000 team steps/s, target ≥ 12,000: NOT met.") in text
    assert "rk4 1e-04 float64: 2.0e-09 m at 0.500 s/sim-s" in text and "tsit5" not in text
    assert "({:.0%})".format(50 / 200) in text
    assert "gravity-only floor 9,000,000." in text and "`jax.vmap`" not in text.split("Profile (f)")[1]
    assert "region mode (what tracking runs) **23.5**, the whole image 1.4 — target ≥ 20: **met**" in text
    # every line names a section, so that a splice can keep the lines of sections not rerun
    assert all(any(f"({s})" in ln for s in report.SECTIONS) for ln in lines if ln.startswith("- "))
    assert report.summary_lines({}) == ["## Summary", "", ""]


def test_header_lines_say_how_the_report_was_made():
    lines = report.header_lines(SimpleNamespace(quick=True), "2030-01-01 00:00 UTC", "1.00 1.00 1.00",
                                "2.00 2.00 2.00", 90.0, "9.9.9")
    text = "\n".join(lines)
    assert lines[0] == "# Benchmarks"
    assert "**QUICK smoke-test run: numbers are not representative.**" in text
    assert "| date | 2030-01-01 00:00 UTC (total wall time 1.5 min) |" in text
    assert "at start 1.00 1.00 1.00; at end 2.00 2.00 2.00" in text and "mujoco 9.9.9" in text
    full = report.header_lines(SimpleNamespace(quick=False), "d", "l", "l", 0.0, "not installed")
    assert "QUICK" not in "\n".join(full) and "mujoco not installed" in "\n".join(full)


def test_write_report_points_plot_links_at_the_plots_and_splices_on_update(tmp_path):
    out = tmp_path / "out" / "BENCHMARKS.md"
    out.parent.mkdir()
    plots = tmp_path / "plots"
    text = _report("day 1", "m", "git a", {"a": "![t](docs/bench/throughput.png)", "c": "C1"})
    report.write_report(text, out, plots, update=False, rerun=["a", "c"])
    written = out.read_text()
    assert "![t](../plots/throughput.png)" in written and "docs/bench/" not in written
    assert written.endswith("C1\n")
    report.write_report(_report("day 2", "m", "git b", {"c": "C2"}), out, plots, update=True, rerun=["c"])
    spliced = out.read_text()
    assert "C2" in spliced and "C1" not in spliced and "throughput.png" in spliced
    assert "kept from the earlier file (day 1, git a, on m)" in spliced


def test_the_levels_target_line_judges_each_level_timed_at_1024():
    from mysim_jax.bench.levels import target_lines

    rows = {"full": {"rate": {256: 900.0, 1024: 999.0}}, "train": {"rate": {1024: 12000.0}}, "fast": {"rate": {1024: 5.0}}}
    assert target_lines(rows) == ["", "**Targets at B = 1024, 10 Hz: `full` 999 team steps/s, target ≥ 1,000: NOT MET; "
                                      "`train` 12,000 team steps/s, target ≥ 12,000: MET**."]
    assert target_lines({"full": {"rate": {256: 900.0}}}) == []
