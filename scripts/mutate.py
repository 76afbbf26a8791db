"""Mutation testing: does the test suite catch plausible one-line bugs?

Each mutation in ``scripts/mutations.yaml`` replaces one exact snippet of library code
(it must occur exactly once in its file) with a plausible bug, and names the tests that
should catch it. The script

1. copies the repository's tracked files (``git ls-files``, as they are in the working
   tree) into a temporary directory — the working tree itself is never modified, so an
   interrupted run leaves nothing behind;
2. checks that every snippet occurs exactly once;
3. runs every distinct test selection on the unmutated copy (all must pass, else it
   reports the failures and stops);
4. for each mutation: applies it in the copy, runs its tests
   (``python -m pytest -x -q -p no:cacheprovider ...`` with ``PYTHONPATH`` and the working
   directory set to the copy, a per-mutation timeout), classifies the mutant, and restores
   the file;
5. writes a Markdown report (``docs/mutation.md`` by default) and prints a summary.

Results: **killed** (a test failed), **survived** (all passed), **timeout** (the tests ran
past ``--timeout``; counted as killed: a mutant that makes the suite hang is caught, if
slowly), **error** (pytest could not run the selection, e.g. a collection error; counted
as *not* killed). Score = (killed + timeout) / total.

Usage::

    python scripts/mutate.py                      # all mutations -> docs/mutation.md
    python scripts/mutate.py --list               # list the mutations
    python scripts/mutate.py --only rk4_renormalisation_removed,baumgarte_2alpha_to_alpha
    python scripts/mutate.py --timeout 300 --report /tmp/mutation.md

With ``--only`` the report is written only if ``--report`` is given.
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
MUTATIONS = ROOT / "scripts" / "mutations.yaml"
DEFAULT_REPORT = ROOT / "docs" / "mutation.md"
PYTEST = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider"]
FIELDS = {"id", "file", "original", "replacement", "description", "tests", "survivor_note"}
REQUIRED = FIELDS - {"survivor_note"}


@dataclass
class Mutation:
    id: str
    file: str
    original: str
    replacement: str
    description: str
    tests: str                      # pytest arguments (node ids, files, -k ...), shell-quoted
    survivor_note: str = ""

    @property
    def selection(self) -> tuple[str, ...]:
        return tuple(shlex.split(self.tests))


@dataclass
class Outcome:
    result: str                     # killed | survived | timeout | error
    seconds: float
    detail: str = ""                # the first failing test, or the tail of the output


def load_mutations(path: Path) -> list[Mutation]:
    entries = yaml.safe_load(path.read_text())
    if not isinstance(entries, list):
        sys.exit(f"{path}: expected a list of mutations")
    problems, mutations, seen = [], [], set()
    for i, entry in enumerate(entries):
        where = f"{path.name}: entry {i}" + (f" ({entry.get('id')})" if isinstance(entry, dict) else "")
        if not isinstance(entry, dict):
            problems.append(f"{where}: not a mapping")
            continue
        missing, unknown = REQUIRED - entry.keys(), entry.keys() - FIELDS
        if missing or unknown:
            problems.append(f"{where}: missing {sorted(missing)}, unknown {sorted(unknown)}")
            continue
        if entry["id"] in seen:
            problems.append(f"{where}: duplicate id")
        seen.add(entry["id"])
        if entry["original"] == entry["replacement"]:
            problems.append(f"{where}: replacement equals the original")
        mutations.append(Mutation(**{k: str(v) for k, v in entry.items()}))
    if problems:
        sys.exit("invalid mutation list:\n  " + "\n  ".join(problems))
    return mutations


def check_snippets(copy: Path, mutations: list[Mutation]) -> None:
    """Every original snippet must occur exactly once in its file; stop otherwise."""
    problems = []
    for m in mutations:
        path = copy / m.file
        if not path.is_file():
            problems.append(f"{m.id}: no file {m.file}")
            continue
        n = path.read_text().count(m.original)
        if n != 1:
            what = "not found" if n == 0 else f"ambiguous ({n} occurrences)"
            problems.append(f"{m.id}: snippet {what} in {m.file}:\n      {m.original!r}")
    if problems:
        sys.exit("mutation snippets do not match the code (update scripts/mutations.yaml):\n  "
                 + "\n  ".join(problems))


def copy_tracked_files(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True, text=True).stdout
    for rel in filter(None, files.split("\0")):
        src = ROOT / rel
        if src.is_file():                       # tracked but deleted in the working tree: skip
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def run_tests(copy: Path, selection: tuple[str, ...], timeout: float) -> Outcome:
    env = dict(os.environ, PYTHONPATH=str(copy), PYTHONDONTWRITEBYTECODE="1")
    start = time.perf_counter()
    try:
        proc = subprocess.run(PYTEST + list(selection), cwd=copy, env=env, capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return Outcome("timeout", time.perf_counter() - start, f"no result after {timeout:g} s")
    seconds = time.perf_counter() - start
    output = proc.stdout + proc.stderr
    if proc.returncode == 0:
        return Outcome("survived", seconds)
    if proc.returncode == 1:
        failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", output, flags=re.MULTILINE)
        return Outcome("killed", seconds, failed[0] if failed else "")
    return Outcome("error", seconds, f"pytest exit code {proc.returncode}: " + " | ".join(output.strip().splitlines()[-3:]))


def baseline(copy: Path, mutations: list[Mutation], timeout: float) -> None:
    """Run each distinct selection unmutated; stop if any fails."""
    selections = list(dict.fromkeys(m.selection for m in mutations))
    failures = []
    for sel in tqdm(selections, desc="baseline (unmutated)", unit="selection"):
        out = run_tests(copy, sel, timeout)
        if out.result != "survived":
            failures.append(f"{' '.join(sel)}: {out.result} {out.detail}")
    if failures:
        sys.exit("the targeted tests do not pass on the unmutated code; fix that first:\n  " + "\n  ".join(failures))


def mutate_and_run(copy: Path, m: Mutation, timeout: float) -> Outcome:
    path = copy / m.file
    original = path.read_text()
    try:
        path.write_text(original.replace(m.original, m.replacement, 1))
        return run_tests(copy, m.selection, timeout)
    finally:
        path.write_text(original)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def write_report(path: Path, mutations, outcomes, wall: float, timeout: float, argv) -> None:
    n = len(mutations)
    caught = sum(o.result in ("killed", "timeout") for o in outcomes.values())
    lines = [
        "# Mutation testing",
        "",
        "Generated by `python scripts/mutate.py` (mutations: `scripts/mutations.yaml`) on "
        f"{datetime.date.today().isoformat()}; command: `{' '.join(['python', 'scripts/mutate.py'] + argv)}`.",
        "",
        "Each mutation is a plausible one-line bug applied to a copy of the repository; its targeted "
        "tests are run with `pytest -x`. *killed*: a test failed (the first failing test is shown); "
        "*timeout*: the tests did not finish within "
        f"{timeout:g} s (counted as killed); *survived*: every targeted test passed; *error*: the tests "
        "could not run (counted as not killed).",
        "",
        f"**Score: {caught}/{n} mutants caught ({100.0 * caught / n:.1f} %).** "
        f"Wall time of the run: {wall / 60:.1f} min (baseline of the unmutated selections included), "
        "on 2 CPU cores shared with other jobs.",
        "",
        "| id | file | description | result | seconds | caught by |",
        "|---|---|---|---|---|---|",
    ]
    for m in mutations:
        o = outcomes[m.id]
        lines.append(f"| `{m.id}` | `{m.file}` | {_cell(m.description)} | {o.result} | {o.seconds:.1f} | "
                     f"{_cell(o.detail) if o.result != 'survived' else ''} |")
    survivors = [m for m in mutations if outcomes[m.id].result in ("survived", "error")]
    lines += ["", "## Survivors", ""]
    if not survivors:
        lines.append("None.")
    for m in survivors:
        note = m.survivor_note.strip() or "**No explanation recorded** (add a `survivor_note` or a test)."
        lines += [f"### `{m.id}` ({outcomes[m.id].result})", "",
                  f"`{m.file}`: `{_cell(m.original.strip())}` → `{_cell(m.replacement.strip())}`. "
                  f"Targeted tests: `{m.tests}`.", "", note, ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines).rstrip() + "\n")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help="comma-separated mutation ids to run")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    parser.add_argument("--report", type=Path, help=f"report path (default {DEFAULT_REPORT.relative_to(ROOT)} "
                                                    "for a full run; none with --only)")
    parser.add_argument("--timeout", type=float, default=240.0, help="per-mutation timeout in s (default 240)")
    parser.add_argument("--mutations", type=Path, default=MUTATIONS, help="mutation list (YAML)")
    args = parser.parse_args(argv)

    mutations = load_mutations(args.mutations)
    if args.list:
        for m in mutations:
            print(f"{m.id:40s} {m.file:36s} {m.description}")
        print(f"{len(mutations)} mutations")
        return 0
    if args.only:
        wanted = [x.strip() for x in args.only.split(",") if x.strip()]
        unknown = sorted(set(wanted) - {m.id for m in mutations})
        if unknown:
            sys.exit(f"--only: unknown mutation ids {unknown} (see --list)")
        mutations = [m for m in mutations if m.id in wanted]
    report = args.report if args.report is not None else (None if args.only else DEFAULT_REPORT)

    start = time.perf_counter()
    outcomes: dict[str, Outcome] = {}
    with tempfile.TemporaryDirectory(prefix="mysim_mutate_") as tmp:
        copy = Path(tmp)
        copy_tracked_files(copy)
        check_snippets(copy, mutations)
        baseline(copy, mutations, args.timeout)
        bar = tqdm(mutations, desc="mutants", unit="mutant")
        for m in bar:
            bar.set_postfix_str(m.id)
            outcomes[m.id] = mutate_and_run(copy, m, args.timeout)
            tqdm.write(f"{outcomes[m.id].result:9s} {outcomes[m.id].seconds:6.1f} s  {m.id}")
    wall = time.perf_counter() - start

    caught = sum(o.result in ("killed", "timeout") for o in outcomes.values())
    print(f"\n{caught}/{len(mutations)} mutants caught ({100.0 * caught / len(mutations):.1f} %) in {wall / 60:.1f} min")
    for result in ("timeout", "survived", "error"):
        ids = [m.id for m in mutations if outcomes[m.id].result == result]
        if ids:
            print(f"{result}: {', '.join(ids)}")
    if report is not None:
        write_report(report, mutations, outcomes, wall, args.timeout, argv)
        print(f"report: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
