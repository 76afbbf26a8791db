#!/usr/bin/env python
"""Map where gradients through the capture task are usable (docs/gradients.md).

    python scripts/gradmap.py configs/train_capture_falling.yaml --out out/gradmap
    python scripts/gradmap.py CONFIG [--levels train full] [--horizons 0.1 0.2 0.5 1 2 6] [--cap full=0.5]
        [--episodes 6] [--pairs 8] [--truncate 2] [--seed 0] [--set KEY=VALUE ...] --out DIR

CONFIG is a capture scene with an ``env:`` block or a training file whose ``env.scene``
is one (its ``env.set`` applied; ``--set`` adds to it). On every level of ``--levels``
(the scene's ``levels:``, or ``full``: the file's own values) it flies ``--episodes``
episodes with the scripted team, starts windows at three segments of each (free flight,
a tether's slack/taut switch, the target's first contact with the net) and, for every
horizon of ``--horizons`` seconds (those above ``--cap LEVEL=SECONDS`` left out on that
level), compares the autodiff gradient of a smooth capture objective, with respect to the
team's parameters and to the rollout's actions, with a randomised-smoothing estimate
from ``--pairs`` antithetic pairs. ``--truncate M`` also measures the backward pass
truncated to M policy steps. Writes ``gradmap.json``, ``gradmap.csv``, ``gradmap.md``,
``gradmap_norm.png`` and ``gradmap_cosine.png`` into OUT (mysim_jax/grad/gradmap_run.py).

Every input is checked before anything is compiled: a problem is a one-line error, exit
code 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import sys

from mysim_jax.core.cli import add_set_argument


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="capture scene (with env:) or training file (with env.scene)")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--levels", nargs="+", default=["train", "full"], help="fidelity levels (default train full)")
    parser.add_argument("--horizons", nargs="+", type=float, default=[0.1, 0.2, 0.5, 1.0, 2.0, 6.0],
                        help="horizons in s (default 0.1 0.2 0.5 1 2 6)")
    parser.add_argument("--cap", nargs="*", default=["full=0.5"], metavar="LEVEL=SECONDS",
                        help="longest horizon on a level (default full=0.5: a step of the level full costs ~40x "
                             "one of train)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes per level (default 6)")
    parser.add_argument("--pairs", type=int, default=8, help="antithetic pairs of the smoothing estimate (default 8)")
    parser.add_argument("--truncate", nargs="*", type=int, default=[2],
                        help="also measure the backward pass truncated to these policy steps (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed of the episodes and samples (default 0)")
    add_set_argument(parser, "env.randomize.wind_force=null", "a scene value")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def _caps(items) -> dict:
    caps = {}
    for item in items:
        level, sep, value = item.partition("=")
        try:
            caps[level.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not level.strip() or not caps[level.strip()] > 0:
            raise ValueError(f"--cap {item!r}: expected LEVEL=SECONDS with SECONDS > 0")
    return caps


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from mysim_jax.config.scene import ConfigError
    from mysim_jax.grad.gradmap import MapSettings, check_settings, level_settings
    from mysim_jax.mappo.config import capture_scenes
    from mysim_jax.io.output import OutputError, check_output_dir

    try:
        caps = _caps(args.cap)
        settings = MapSettings(horizons=tuple(args.horizons), episodes=args.episodes, pairs=args.pairs,
                               truncate=tuple(args.truncate), seed=args.seed)
        check_settings(settings)
        if len(set(args.levels)) != len(args.levels):
            raise ValueError(f"--levels {' '.join(args.levels)}: a level is listed twice")
        configs = capture_scenes(args.config, args.levels, args.overrides)
        for level, config in configs.items():
            check_settings(level_settings(settings, caps.get(level)), 1.0 / config.env.policy_rate, config.sim.t_end)
        out = check_output_dir(args.out)
    except (ValueError, ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.core.precision import use_precision

    use_precision(*(c.sim.precision for c in configs.values()))

    from mysim_jax.grad.gradmap_run import run_gradmap

    run_gradmap(configs, settings, out, args.config, caps=caps, progress=not args.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
