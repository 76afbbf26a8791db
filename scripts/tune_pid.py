#!/usr/bin/env python
"""Tune the quadrotor PID gains by gradient descent through the closed-loop simulation.

    python scripts/tune_pid.py configs/uav_track_large.yaml --out out/tune \\
        [--heldout configs/uav_track_heldout.yaml] [--iterations 40] [--checkpoint] [--horizon-study]

Differentiates the mean squared tracking error over the scene's run (or ``--horizon``
seconds) with respect to the log-gains (``gain = gain₀ exp(θ)``: positive, relative
steps; see mysim_jax/tuning/gains.py) and runs Adam (global-norm clipping, non-finite
updates skipped). Writes into OUT:

* ``gains.yaml`` — the tuned gains (``simulate.py SCENE --gains OUT/gains.yaml``);
* ``tuned_config.yaml`` — the scene with the tuned gains (``simulate.py`` runs it as is);
* ``loss_curve.png`` — RMS tracking error and gradient norm per iteration;
* ``metrics.json`` — RMS / max errors before and after, on the scene and on every
  ``--heldout`` scene (same evaluation as ``simulate.py``'s metrics.json);
* ``config.yaml`` — the resolved input scene;
* with ``--horizon-study``: ``horizon_study.json`` and ``horizon_study.md`` — gradient
  norm, truncation error, time and memory against the horizon.
"""

from __future__ import annotations

import argparse
import sys

from mysim_jax.core.cli import add_set_argument


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML scene with controlled quadrotors")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--heldout", action="append", default=[], metavar="CONFIG",
                        help="scene to evaluate before/after, not tuned on (repeatable)")
    parser.add_argument("--iterations", type=int, default=40, help="optimiser steps (default 40)")
    parser.add_argument("--lr", type=float, default=0.05, help="Adam learning rate on log-gains (default 0.05)")
    parser.add_argument("--clip", type=float, default=1.0, help="global-norm gradient clip (default 1.0)")
    parser.add_argument("--horizon", type=float, default=None, help="loss horizon in s (default: sim.t_end)")
    parser.add_argument("--every", type=int, default=10, help="loss sample / checkpoint interval in steps")
    parser.add_argument("--checkpoint", action="store_true",
                        help="rematerialise chunks of --every steps in the backward pass (memory ~100x lower "
                             "on long horizons, compile ~2x slower; see --horizon-study)")
    parser.add_argument("--horizon-study", action="store_true",
                        help="also measure gradient norm, truncation error, time and memory against the horizon")
    parser.add_argument("--study-horizons", default="1,2.5,5,10,20", help="horizons (s) for --horizon-study")
    add_set_argument(parser, "sim.dt=5e-4", "a config value")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.iterations < 0 or args.lr <= 0 or args.clip <= 0 or args.every < 1:
        print("error: --iterations >= 0, --lr > 0, --clip > 0, --every >= 1", file=sys.stderr)
        return 2

    from mysim_jax.config.scene import ConfigError, load_config
    from mysim_jax.io.output import OutputError, check_output_dir

    try:
        config = load_config(args.config, args.overrides)
        heldout = [load_config(path) for path in args.heldout]
        out_dir = check_output_dir(args.out)
    except (ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path, cfg in [(args.config, config)] + list(zip(args.heldout, heldout)):
        if not cfg.quadrotors or cfg.quadrotors[0].controller is None:
            print(f"error: {path}: quadrotors: the scene has no controlled quadrotor to tune", file=sys.stderr)
            return 2
    if args.horizon is not None and args.horizon <= 0:
        print("error: --horizon must be positive", file=sys.stderr)
        return 2

    from mysim_jax.core.precision import use_precision

    use_precision(*(c.sim.precision for c in [config] + heldout))

    from mysim_jax.tuning.run import TuneSettings, tune_scene

    horizons = tuple(float(h) for h in args.study_horizons.split(",") if h.strip()) if args.horizon_study else ()
    settings = TuneSettings(iterations=args.iterations, lr=args.lr, clip=args.clip, horizon=args.horizon,
                            every=args.every, checkpoint=args.checkpoint, study_horizons=horizons,
                            progress=not args.no_progress)
    try:
        tune_scene(config, list(zip(args.heldout, heldout)), out_dir, settings, args.config)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
