#!/usr/bin/env python
"""Evaluate a capture team on many episodes of a capture scene's environment.

    python scripts/evaluate.py configs/capture_env_falling.yaml --policy scripted --episodes 200 --out out/eval
    python scripts/evaluate.py CONFIG --policy my_policy.py --episodes 64 --batch 16 --seed 1 --out DIR

``--policy`` is ``scripted`` (the scripted intercept team), ``random`` (uniform actions),
a trained policy (the ``policy/`` folder of a ``scripts/train.py`` run), or a Python file
defining ``make_policy(env, params)`` that returns ``policy(key, obs, state, params) ->
actions (n_agents, 3)`` for one environment (mysim_jax/mappo/policies.py). The scene needs
``net:``, ``target:`` and controlled ``quadrotors:``; a scene without an ``env:`` block
is evaluated with the defaults (``env: {}``, a note says so and ``config.yaml`` records
them).

``--episodes N`` episodes run ``--batch B`` environments side by side
(mysim_jax/tasks/evaluate.py: every slot runs the same number of episodes, so short
episodes are not favoured). Writes into OUT:

* ``metrics.json`` — success, failure and timeout rates with 95 % Wilson intervals, mean
  reward terms, return and length, wall time; the config, policy, episodes, batch, seed;
  the recorded episode's outcome (the environment's verdict) and, under ``capture``,
  simulate.py's summary of it (both count the hold from the first held sample);
* ``episodes.csv`` — one row per episode (slot, flags, length, return, every term);
* ``outcomes.png``, ``reward_terms.png``, ``lengths.png``, ``returns.png``;
* the first episode of slot 0 replayed and recorded (mysim_jax/tasks/episode.py) in the
  format of ``scripts/simulate.py``: ``trajectory.csv`` on the policy-step grid (ending
  at the episode's last, pre-reset state), ``config.yaml``, the ``capture_*.png`` plots
  and ``capture.gif`` (skipped with ``--no-animation``), plus ``episode_steps.csv`` and
  ``episode_rewards.png`` (its per-step rewards).

``--compare POLICY`` also runs a second team (any ``--policy`` value, e.g. ``scripted``)
on the same episodes (episode ``i`` is drawn from its own key, whichever team flies it)
and writes ``comparison.json`` (both success rates and their paired difference with its
95 % interval) and ``comparison_episodes.csv`` (each team's outcome per episode).

A trained policy is flown only on an environment whose observations and actions mean what
they meant in training (setpoint mode, policy rate, action scale, observation layout,
target; ``policy.json`` records them): another is refused with the differences named,
unless ``--allow-mismatch`` (a deliberate test). The fidelity level, the ranges and
``--perception`` may differ: judging a policy there is what evaluations are for.

``--perception FILE`` evaluates the team flying on estimates instead of true states: FILE is
an ``env.perception`` block (YAML: ``uav_position``, ``uav_velocity``, ``target_position``,
``target_velocity``, each ``{sigma, correlation_time}``; mysim_jax/config/env.py),
e.g. the one ``scripts/perception_gap.py fit`` writes from measured estimation errors.
``metrics.json`` then records it under ``perception``. ``scripts/perception_gap.py compare``
sets such a run against one on true states over the same episodes (``--batch`` equal to
``--episodes``).

Every input (config, overrides, OUT, policy, numbers) is checked before anything is
compiled; a problem is a one-line error, exit code 2, and nothing is written. Outputs are
written to a temporary folder and moved into OUT only when complete.
"""

from __future__ import annotations

import argparse
import json
import sys

from mysim_jax.core.cli import add_set_argument, add_team_arguments


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML capture scene file")
    add_team_arguments(parser)
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed of the whole evaluation (default 0)")
    add_set_argument(parser, "env.policy_rate=10", "a config value")
    parser.add_argument("--perception", metavar="FILE",
                        help="fly on estimates: a YAML env.perception block (uav_position, ..., target_velocity)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--no-animation", action="store_true", help="do not write capture.gif (slow)")
    return parser


def _checked_inputs(args):
    """The scene (with the perception block and its env: defaults), the output folder, a
    note when the scene had no env: block, and the perception block; before JAX is imported.
    Raises ConfigError, OutputError or PolicyError."""
    from mysim_jax.config.env import drawn_value_problems
    from mysim_jax.config.overrides import override_list
    from mysim_jax.config.scene import ConfigError, load_config
    from mysim_jax.io.output import check_output_dir
    from mysim_jax.mappo.policies import check_policy_spec
    from mysim_jax.tasks.perception_gap import read_perception_block

    perception = None
    if args.perception is not None:
        perception = read_perception_block(args.perception)
        args.overrides = override_list(args.overrides, then={"env.perception": json.dumps(perception)})
    config = load_config(args.config, args.overrides)
    ignored = drawn_value_problems(config, args.overrides)
    if ignored:
        raise ConfigError("; ".join(ignored))
    missing = [b for b, v in (("net", config.net), ("target", config.target), ("quadrotors", config.quadrotors))
               if not v]
    if missing:
        raise ConfigError(f"{args.config}: not a capture scene: it has no {' and no '.join(missing)} block")
    env_note = None
    if config.env is None:
        config = load_config(args.config, override_list(args.overrides, first=["env={}"]))
        env_note = f"note: {args.config} has no env: block; evaluating with the defaults (env: {{}})"
    out = check_output_dir(args.out)
    check_policy_spec(args.policy)
    if args.compare is not None:
        check_policy_spec(args.compare)
    return config, out, env_note, perception


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    for flag, value, low in (("--episodes", args.episodes, 1), ("--batch", args.batch, 1), ("--seed", args.seed, 0)):
        if value is not None and value < low:
            return _error(f"{flag} {value}: must be at least {low}")
    if args.batch is not None and args.batch > args.episodes:
        print(f"note: --batch {args.batch} is more than --episodes {args.episodes}: running {args.episodes} "
              "side by side", file=sys.stderr)
    args.batch = min(64 if args.batch is None else args.batch, args.episodes)

    from mysim_jax.config.scene import ConfigError
    from mysim_jax.io.output import OutputError
    from mysim_jax.mappo.policies import PolicyError

    try:
        config, out, env_note, perception = _checked_inputs(args)
    except (ConfigError, OutputError, PolicyError) as err:
        return _error(str(err))

    import jax

    from mysim_jax.core.precision import use_precision

    use_precision(config.sim.precision)

    from mysim_jax.mappo.policies import make_checked_policy
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.evaluate import run_episodes, run_two_teams
    from mysim_jax.tasks.report import comparison_line, summary_line, write_comparison, write_evaluation

    try:
        env, params = make_env(config)
    except (ConfigError, ValueError) as err:
        return _error(f"{args.config}: {err}")
    try:
        policy = make_checked_policy(env, params, args.policy, "--policy", args.allow_mismatch)
        other = (make_checked_policy(env, params, args.compare, "--compare", args.allow_mismatch)
                 if args.compare is not None else None)
    except PolicyError as err:
        return _error(str(err))
    if env_note:
        print(env_note, file=sys.stderr)

    key = jax.random.PRNGKey(args.seed)
    if other is None:
        stats = run_episodes(env, params, policy, args.episodes, args.batch, key, progress=not args.no_progress)
    else:
        stats, base = run_two_teams(env, params, policy, other, args.episodes, args.batch, key,
                                    progress=not args.no_progress)
    metrics = write_evaluation(out, config, env, params, policy, policy_name=args.policy, episodes=args.episodes,
                               batch=args.batch, seed=args.seed, config_path=args.config, overrides=args.overrides,
                               env_note=env_note, progress=not args.no_progress, animate=not args.no_animation,
                               extra={"perception": perception}, stats=stats)
    print(summary_line(config.name, args.policy, metrics, out))
    if other is not None:
        result = write_comparison(out, stats, base, names=("policy", "compare"), seed=args.seed,
                                  extra={"policy": args.policy, "compare": args.compare})
        print(comparison_line(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
