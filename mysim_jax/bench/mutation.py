"""Mutation testing (``scripts/mutate.py``): apply plausible one-line bugs from
``scripts/mutations.yaml`` one at a time to a copy of the repository, run the tests that
should catch each, and report which were caught. The working tree is never modified."""

from __future__ import annotations

import datetime
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from tqdm import tqdm

from mysim_jax.core.machine import machine

ROOT = Path(__file__).resolve().parents[2]     # the repository
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
        f"{datetime.date.today().isoformat()} on {machine()}; command: "
        f"`{' '.join(['python', 'scripts/mutate.py'] + argv)}`.",
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
