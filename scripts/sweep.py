#!/usr/bin/env python
"""Evaluate a capture team over a grid of scene overrides, on the same episodes at every point.

    python scripts/sweep.py configs/capture_env_falling.yaml --set level=train --policy scripted --compare random \\
        --vary "env.randomize.wind_force={low: [0, 0, 0], high: [0, 0, 0]},{low: [0.3, 0, 0], high: [0.3, 0, 0]}" \\
        --episodes 200 --out out/sweep_wind
    python scripts/sweep.py SCENE --policy P [--compare Q] --vary KEY=v1,v2,... [--vary KEY2=...] --episodes N \\
        [--batch B] [--seed S] [--set KEY=VALUE ...] [--allow-mismatch] [--no-progress] --out DIR

SCENE is a capture scene file (``net:``, ``target:``, controlled ``quadrotors:``; without
an ``env:`` block it is evaluated with the defaults, ``env: {}``, and a note says so).
``--policy`` and ``--compare`` take what ``scripts/evaluate.py --policy`` takes:
``scripted``, ``random``, a trained policy folder (``RUN/policy``) or a Python file
defining ``make_policy(env, params)`` (mysim_jax/mappo/policies.py).

``--vary KEY=v1,v2,...`` (repeatable) is one axis of the grid; every combination of the
axes' values is evaluated (the first axis varies slowest). Values are YAML, as ``--set``
values, split only on the commas outside brackets, braces and quotes, so
``--vary "env.randomize.target_mass={low: 0.1, high: 0.1},{low: 0.3, high: 0.3}"`` is two
values. ``--vary seed=2026,2027`` varies the evaluation seed (other episodes) instead of a
scene value; ``--vary level=train,full`` the scene's fidelity level. A point's overrides
are applied after ``--set``'s; a key may not be in both.

Same episodes: episode ``i`` of every point with seed ``S`` is drawn from
``jax.random.PRNGKey(S)``, for both teams, exactly as ``scripts/evaluate.py --seed S``
draws it (mysim_jax/tasks/evaluate.py), so points differ only in what was varied.

Writes into DIR (mysim_jax/tasks/grid.py):

* ``sweep.csv`` — one row per point and team: the varied values, seed, team (``policy`` /
  ``compare``) and its spec, episodes, successes, success rate with its 95 % Wilson
  interval, timeout rate, each failure's count, mean length (policy steps), mean return;
  with ``--compare``, on the policy's row the paired difference policy - compare with its
  95 % interval;
* ``sweep.json`` — the same rows, the command line, scene, overrides, seeds, episodes,
  batch, both specs, wall time and machine;
* ``success_<KEY>.png`` per varied key (dots as ``_``) — success rate against the key's
  values, one line per combination of the other keys' values (dashed: the compared team).

Every input (scene, ``--set``, every grid point's overrides, the specs, DIR, numbers) is
checked before anything is compiled, and each team is made and traced on every point's
environment before the first point runs: a problem is a one-line error, exit code 2, and
nothing is written. Outputs are written to a temporary folder and moved into DIR only
when complete. While it runs, each point saves its progress every 5 minutes into
``.<DIR name>.resume/`` beside DIR: the same command run again after a stop goes on from
there, with the numbers an uninterrupted run gives.
"""

from __future__ import annotations

import argparse
import shlex
import sys

from mysim_jax.core.cli import add_set_argument, add_team_arguments


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", help="YAML capture scene file with an env: block")
    add_team_arguments(parser, "episodes per point and team (>= 1)")
    parser.add_argument("--vary", action="append", required=True, metavar="KEY=v1,v2,...",
                        help="one axis of the grid: a scene key (or seed) and its values (YAML, split on the commas "
                        "outside brackets); repeat for more axes")
    parser.add_argument("--seed", type=int, default=None, help="PRNG seed of every point's episodes (default 0; "
                        "or vary it with --vary seed=...)")
    add_set_argument(parser, "level=train", "a scene value at every point")
    parser.add_argument("--no-progress", action="store_true", help="hide the per-point episode progress bars")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    for flag, value, low in (("--episodes", args.episodes, 1), ("--batch", args.batch, 1), ("--seed", args.seed, 0)):
        if value is not None and value < low:
            return _error(f"{flag} {value}: must be at least {low}")
    if args.batch is not None and args.batch > args.episodes:
        print(f"note: --batch {args.batch} is more than --episodes {args.episodes}: running {args.episodes} "
              "side by side", file=sys.stderr)

    from mysim_jax.config.scene import ConfigError
    from mysim_jax.io.output import OutputError
    from mysim_jax.mappo.policies import PolicyError, check_policy_spec
    from mysim_jax.tasks.grid import SweepError, one_line, plan_sweep

    try:
        plan = plan_sweep(args.scene, args.overrides, args.vary, seed=args.seed, episodes=args.episodes,
                          batch=64 if args.batch is None else args.batch, policy=args.policy, compare=args.compare,
                          out=args.out)
        check_policy_spec(args.policy, "--policy")
        if args.compare is not None:
            check_policy_spec(args.compare, "--compare")
    except (ConfigError, OutputError, PolicyError) as err:
        return _error(one_line(str(err)))

    from mysim_jax.core.precision import use_precision

    use_precision(plan.precision)

    from mysim_jax.mappo.policies import make_checked_policy
    from mysim_jax.tasks.grid import run_sweep

    def make_policy(env, params, spec, flag):
        return make_checked_policy(env, params, spec, flag, args.allow_mismatch)

    command = shlex.join(["python", *(sys.argv if argv is None else ["scripts/sweep.py", *argv])])
    try:
        record = run_sweep(plan, make_policy, progress=not args.no_progress, command=command,
                           extra={"allow_mismatch": args.allow_mismatch})
    except SweepError as err:
        return _error(str(err))
    print(f"{record['scene_name']}: {len(plan.points)} points x {plan.episodes} episodes in {record['wall_s']:.0f} s "
          f"(compile included); wrote {plan.out}/sweep.csv, sweep.json and {', '.join(record['plots'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
