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
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

from mysim_jax.bench.mutation import (DEFAULT_REPORT, MUTATIONS, ROOT, Outcome, baseline, check_snippets,
                                      copy_tracked_files, load_mutations, mutate_and_run, write_report)


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help="comma-separated mutation ids to run")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    parser.add_argument("--report", type=Path, help=f"report path (default {DEFAULT_REPORT.relative_to(ROOT)} "
                                                    "for a full run; none with --only)")
    parser.add_argument("--timeout", type=float, default=240.0, help="per-mutation timeout in s (default 240)")
    parser.add_argument("--mutations", type=Path, default=MUTATIONS, help="mutation list (YAML)")
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)

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
