#!/usr/bin/env python
"""Teams flown on the same episodes, compared episode by episode after the fact.

    python scripts/pair.py runs/new_team/eval runs/shipped/eval runs/shipped/eval:compare
    python scripts/pair.py A B [C ...] --out pairing.json

Each argument is a ``scripts/evaluate.py`` folder (its ``--policy`` team) or ``FOLDER:compare``
(its ``--compare`` team). The first team is paired with each of the others: a Markdown
table of the success rates (95 % Wilson intervals) and the paired differences (Newcombe's
interval), with the episodes only one of the two caught. The folders must have flown the
same episodes (one scene, the same ``--seed`` and ``--episodes``; the policy, ``--batch``,
``--set`` and ``--perception`` may differ): otherwise a one-line error names what differs,
exit code 2 (mysim_jax/tasks/pairing.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", metavar="FOLDER[:compare]",
                        help="scripts/evaluate.py folders; the first is paired with each of the others")
    parser.add_argument("--out", help="also write the result as JSON here")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from mysim_jax.tasks.pairing import PairingError, pair_outcomes, pairing_table

    try:
        result = pair_outcomes(args.folders)
    except PairingError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2))
    print(f"{result['scene']}, {result['episodes']} episodes of seed {result['seed']} "
          f"({result['method']}):\n\n{pairing_table(result)}")
    for row in result["teams"]:
        extra = [o for o in row["overrides"] if not o.startswith("env.perception=")]
        extra += ["--perception"] if row["perception"] else []
        if extra:
            print(f"  {row['folder']}: {' '.join(extra)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
