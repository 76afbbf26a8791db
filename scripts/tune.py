#!/usr/bin/env python
"""Tune a capture scene's scripted team on the smooth capture objective (docs/gradients.md).

    python scripts/tune.py configs/capture_env_maneuvering.yaml --method cmaes --budget 20000 --out out/tune
    python scripts/tune.py CONFIG --method grad|cmaes|random --budget TEAM_STEPS [--episodes 4] [--horizon-s H]
        [--level train] [--truncate M] [--batch 8] [--box -0.5 0.5] [--vertical-weight 0] [--ground-weight 0] [--seed 0]
        [--judge-episodes 1000] [--judge-level full] [--judge-seed 12345] [--set KEY=VALUE ...] --out DIR

CONFIG is a capture scene with an ``env:`` block and a scripted ``team:`` or a training
file whose ``env.scene`` is one (its ``env.set`` applied; ``--set`` adds to it). The
fields of the scene's ``team:`` block become a vector of relative changes (``--box``:
its bounds, narrowed to what the team config accepts); their value is the mean, over
``--episodes`` fixed training episodes at ``--level`` (every candidate flies the same
ones), of the smooth capture objective over ``--horizon-s`` seconds from the reset
(default: the whole episode). ``--method`` minimises it within ``--budget`` simulated team
steps (one evaluation costs episodes x horizon steps; ``grad`` is gradient descent
through the simulator, truncated to ``--truncate`` policy steps if given). Then, unless
``--judge-episodes 0``, the tuned team and the configured team fly the same fresh
episodes at ``--judge-level`` (an evaluation seeded with ``--judge-seed``) and the capture
verdict decides. Writes ``tune.json``, ``history.csv``, ``tune_best.png`` and
``judged.json`` into OUT (mysim_jax/grad/tune_run.py).

**The design** instead of the team (``--design KEY=LOW:HIGH ...``, mysim_jax/grad/design.py):
numeric scene values (e.g. ``net.size=1.5:3.5 net.tethers.length=0.6:2.0``) searched within
their bounds by ``--method cmaes`` or ``random`` for the scene's scripted team, valued by
the miss rate of the capture verdict on ``--episodes`` fixed episodes at ``--level``; the
tethered UAVs' starts move with the net's corners and the tethers' length. Each candidate
is another scene and compiles its own program. A value the tuning level sets itself (e.g.
``net.line.EA`` at ``train``) is refused: tune it at a level that keeps it. Judged as the
team is (``judged.json``); ``tune.json`` holds the ``--set`` entries of the tuned scene:

    python scripts/tune.py configs/train_capture_falling.yaml --design net.size=1.5:3.5 --method cmaes --budget 40000 \
        --episodes 64 --judge-episodes 200 --judge-level train --out out/design

Every input is checked before anything is compiled: a problem is a one-line error, exit
code 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import sys

from mysim_jax.core.cli import add_set_argument

METHODS = ("grad", "cmaes", "random")


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="capture scene (with env: and team:) or training file (with env.scene)")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--method", required=True, help="grad, cmaes or random")
    parser.add_argument("--budget", type=int, required=True, help="simulated team steps to spend")
    parser.add_argument("--episodes", type=int, default=4, help="fixed training episodes per evaluation (default 4)")
    parser.add_argument("--horizon-s", type=float, default=None,
                        help="objective's horizon from the reset in s (default: the whole episode)")
    parser.add_argument("--level", default="train", help="fidelity level tuned on (default train)")
    parser.add_argument("--truncate", type=int, default=None, help="grad: truncate the backward pass to M policy steps")
    parser.add_argument("--batch", type=int, default=8, help="random: candidates per batch (default 8)")
    parser.add_argument("--box", nargs=2, type=float, default=None, metavar=("LOWER", "UPPER"),
                        help="relative bounds of every team field (default -0.5 0.5: +-50 %%)")
    parser.add_argument("--design", nargs="+", default=None, metavar="KEY=LOW:HIGH",
                        help="tune these scene values within their bounds instead of the team (cmaes or random)")
    parser.add_argument("--vertical-weight", type=float, default=0.0, metavar="W",
                        help="weight [m/m] of the target's height off the net's centre at the horizon's end in the "
                             "objective (default 0: no such term)")
    parser.add_argument("--ground-weight", type=float, default=0.0, metavar="W",
                        help="weight [m/m] of the target's centre under 0.5 m above the ground at the horizon's end "
                             "(default 0: no such term)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the training episodes and the search (default 0)")
    parser.add_argument("--judge-episodes", type=int, default=1000,
                        help="fresh episodes judging tuned vs configured team (default 1000; 0: no judging)")
    parser.add_argument("--judge-level", default="full", help="fidelity level of the judging (default full)")
    parser.add_argument("--judge-seed", type=int, default=12345, help="evaluation seed of the judging (default 12345)")
    parser.add_argument("--judge-batch", type=int, default=64, help="judging episodes side by side (default 64)")
    add_set_argument(parser, "env.randomize.wind_force=null", "a scene value")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return parser


def _scene_configs(path: str, levels, overrides) -> dict:
    """``{level: SceneConfig}`` of a capture scene with a scripted team; ConfigError else."""
    from mysim_jax.config.scene import ConfigError
    from mysim_jax.mappo.config import capture_scenes

    configs = capture_scenes(path, levels, overrides)
    for config in configs.values():
        if config.team is not None and config.team.policy == "hold":
            raise ConfigError(f"{path}: team.policy: hold has nothing to tune")
    return configs


def _checked(args) -> tuple[dict, dict]:
    """``(configs, settings)``; ValueError or ConfigError naming the problem."""
    if args.method not in METHODS:
        raise ValueError(f"--method {args.method!r}: expected one of {', '.join(METHODS)}")
    if args.design is not None:
        return _checked_design(args)
    if args.box is None:
        args.box = [-0.5, 0.5]
    for flag, value, low in (("--episodes", args.episodes, 1), ("--batch", args.batch, 1),
                             ("--judge-episodes", args.judge_episodes, 0), ("--judge-batch", args.judge_batch, 1),
                             ("--seed", args.seed, 0), ("--judge-seed", args.judge_seed, 0)):
        if value < low:
            raise ValueError(f"{flag} {value}: must be at least {low}")
    for flag, value in (("--vertical-weight", args.vertical_weight), ("--ground-weight", args.ground_weight)):
        if not value >= 0.0:
            raise ValueError(f"{flag} {value:g}: must be >= 0")
    if args.truncate is not None and args.truncate < 1:
        raise ValueError(f"--truncate {args.truncate}: must be at least 1")
    if not args.box[0] < 0.0 < args.box[1]:
        raise ValueError(f"--box {args.box[0]:g} {args.box[1]:g}: expected LOWER < 0 < UPPER (0: the configured team)")
    levels = [args.level] + ([args.judge_level] if args.judge_episodes > 0 else [])
    configs = _scene_configs(args.config, levels, args.overrides)
    config = configs[args.level]
    policy_dt, episode = 1.0 / config.env.policy_rate, config.sim.t_end
    max_steps = int(round(episode / policy_dt))
    horizon = None
    if args.horizon_s is not None:
        horizon = int(round(args.horizon_s / policy_dt))
        if not 1 <= horizon <= max_steps:
            raise ValueError(f"--horizon-s {args.horizon_s:g}: expected one policy step ({policy_dt:g} s) to the "
                             f"episode ({episode:g} s)")
    cost = args.episodes * (max_steps if horizon is None else horizon)
    if args.budget < cost:
        raise ValueError(f"--budget {args.budget}: less than one evaluation ({args.episodes} episodes x "
                         f"{cost // args.episodes} steps = {cost} team steps)")
    settings = {"config": args.config, "method": args.method, "budget": args.budget, "episodes": args.episodes,
                "horizon": horizon, "horizon_s": args.horizon_s, "level": args.level, "truncate": args.truncate,
                "batch": args.batch, "box": tuple(args.box), "seed": args.seed, "overrides": list(args.overrides),
                "judge_episodes": args.judge_episodes, "judge_level": args.judge_level, "judge_seed": args.judge_seed,
                "judge_batch": args.judge_batch, "vertical_weight": args.vertical_weight,
                "ground_weight": args.ground_weight}
    return configs, settings


def _checked_design(args) -> tuple[dict, dict]:
    """``--design``'s ``(checked, settings)``: the design problem at the tuning level and
    the scene loader at the judging level, checked; ValueError or ConfigError naming the
    problem."""
    from mysim_jax.grad.design import DESIGN_METHODS, DesignField, DesignProblem
    from mysim_jax.mappo.config import capture_scenes

    if args.method not in DESIGN_METHODS:
        raise ValueError(f"--method {args.method} with --design: expected one of {', '.join(DESIGN_METHODS)} (a "
                         "design candidate is another scene and its value a count: no gradient to follow)")
    for flag, given in (("--box", args.box is not None), ("--horizon-s", args.horizon_s is not None),
                        ("--truncate", args.truncate is not None), ("--vertical-weight", args.vertical_weight != 0.0),
                        ("--ground-weight", args.ground_weight != 0.0)):
        if given:
            raise ValueError(f"{flag} is for tuning the team; with --design each value's bounds are in KEY=LOW:HIGH "
                             "and the value is the miss rate over whole episodes")
    for flag, value, low in (("--episodes", args.episodes, 1), ("--batch", args.batch, 1),
                             ("--judge-episodes", args.judge_episodes, 0), ("--judge-batch", args.judge_batch, 1),
                             ("--seed", args.seed, 0), ("--judge-seed", args.judge_seed, 0)):
        if value < low:
            raise ValueError(f"{flag} {value}: must be at least {low}")
    fields = [DesignField.parse(text) for text in args.design]
    capture_scenes(args.config, [args.level], args.overrides)      # the scene itself first, its own errors

    def loader(level):
        return lambda extra: capture_scenes(args.config, [level], [*args.overrides, *extra])[level]

    problem = DesignProblem(loader(args.level), fields, episodes=args.episodes, seed=args.seed, batch=args.episodes)
    if args.judge_episodes > 0:
        capture_scenes(args.config, [args.judge_level], args.overrides)
    if args.budget < problem.steps_per_evaluation:
        raise ValueError(f"--budget {args.budget}: less than one design's evaluation ({args.episodes} episodes x "
                         f"{problem.max_steps} steps = {problem.steps_per_evaluation} team steps)")
    settings = {"config": args.config, "design": list(args.design), "method": args.method, "budget": args.budget,
                "episodes": args.episodes, "level": args.level, "batch": args.batch, "seed": args.seed,
                "overrides": list(args.overrides), "judge_episodes": args.judge_episodes,
                "judge_level": args.judge_level, "judge_seed": args.judge_seed, "judge_batch": args.judge_batch}
    checked = {"problem": problem, "judge": loader(args.judge_level) if args.judge_episodes > 0 else None,
               "precision": problem.base.sim.precision}
    return checked, settings


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from mysim_jax.config.scene import ConfigError
    from mysim_jax.io.output import OutputError, check_output_dir

    try:
        configs, settings = _checked(args)
        out = check_output_dir(args.out)
    except (ValueError, ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.core.precision import use_precision

    if args.design is not None:
        from mysim_jax.grad.tune_run import run_design

        use_precision(configs["precision"])
        run_design(configs["problem"], settings, out, load_judge=configs["judge"], progress=not args.no_progress)
        return 0
    use_precision(*(c.sim.precision for c in configs.values()))

    from mysim_jax.grad.objective import ObjectiveWeights
    from mysim_jax.grad.tune_run import run_tune

    judge_config = configs.get(args.judge_level) if args.judge_episodes > 0 else None
    run_tune(configs[args.level], settings, out, judge_config=judge_config,
             weights=ObjectiveWeights(vertical=args.vertical_weight, ground=args.ground_weight), progress=not args.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
