#!/usr/bin/env python
"""Run a declared stress suite: a team under one-factor shifts beyond its training ranges,
paired against another team on the same episodes.

    python scripts/stress.py configs/stress/maneuvering.yaml --out docs/robustness/maneuvering
    python scripts/stress.py STRESS_FILE --out DIR [--episodes N] [--no-progress]

STRESS_FILE (``configs/stress/*.yaml``; mysim_jax/tasks/stress.py describes it) names the
scene, the two teams, the level, the episodes and their seed, the factors with their values
and the criterion. The nominal point (every draw at its training range) and each factor
run as a sweep (``scripts/sweep.py``'s machinery, mysim_jax/tasks/grid.py) into
``DIR/nominal`` and ``DIR/<factor>``; then ``DIR`` gets ``stress.csv`` and ``stress.json``
(one row per point: both teams' success with 95 % Wilson intervals, the paired difference
with its interval, the fraction of the nominal success, the verdict at each factor's judged
value), ``table.md`` (the docs' table) and ``stress.png`` (a panel per factor).

A factor whose ``DIR/<factor>/sweep.json`` already holds the same points, episodes, seed and
teams is read instead of run again, and a point that was running goes on from the progress
it saved (every 5 minutes, in ``DIR/.<factor>.resume/``; with the same code and team files
only), so an interrupted suite resumes where it stopped with the numbers an uninterrupted
run gives.
``--episodes`` runs fewer (or more) episodes than the file declares, e.g. to try a file.
Every input is checked before anything compiles: a problem is a one-line error, exit code 2.
"""

from __future__ import annotations

import argparse
import shlex
import sys


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stress_file", help="YAML stress file (configs/stress/*.yaml)")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per point and team instead of the file's")
    parser.add_argument("--no-progress", action="store_true", help="hide the per-point episode progress bars")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from mysim_jax.config.scene import ConfigError
    from mysim_jax.io.output import OutputError
    from mysim_jax.mappo.policies import PolicyError, check_policy_spec
    from mysim_jax.tasks.grid import SweepError, one_line
    from mysim_jax.tasks.stress import plan_stress

    try:
        plan = plan_stress(args.stress_file, args.out, args.episodes)
        check_policy_spec(plan.config.policy, "policy")
        check_policy_spec(plan.config.compare, "compare")
    except (ConfigError, OutputError, PolicyError) as err:
        return _error(one_line(str(err)))

    from mysim_jax.mappo.policies import make_checked_policy
    from mysim_jax.tasks.stress import run_stress

    def make_policy(env, params, spec, flag):
        return make_checked_policy(env, params, spec, flag, False)

    command = shlex.join(["python", *(sys.argv if argv is None else ["scripts/stress.py", *argv])])
    try:
        record = run_stress(plan, make_policy, progress=not args.no_progress, command=command)
    except SweepError as err:
        return _error(str(err))
    j = record["judged"]
    print(f"{plan.config.name}: {j['met']} of {j['shifts']} judged shifts meet the criterion"
          + (f" (failing: {', '.join(j['failing'])})" if j["failing"] else "")
          + f"; wrote {plan.out}/stress.csv, stress.json, table.md and stress.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
