#!/usr/bin/env python
"""The perception gap: capture success on true states minus on perceived states.

    # 1. measured estimation errors -> an env.perception block
    python scripts/perception_gap.py fit --uav runs/cap/vio_uav1/metrics.json runs/cap/vio_uav2/metrics.json \\
        --target runs/cap/track/metrics.json --out configs/perception_capture.yaml
    # 2. the same 1000 episodes on true and on perceived states (the same seed: episode i
    #    is drawn alike in both)
    python scripts/evaluate.py SCENE --policy RUN/policy --episodes 1000 --out gap/true
    python scripts/evaluate.py SCENE --policy RUN/policy --episodes 1000 \\
        --perception configs/perception_capture.yaml --out gap/perceived
    # 3. the gap, with intervals
    python scripts/perception_gap.py compare gap/true gap/perceived [--out gap/gap.json]

``fit`` reads the ``error_model`` blocks (Gauss-Markov fits of the unaligned position and
velocity errors) of ``scripts/perceive.py`` VIO runs (``--uav``, one per UAV) and of its
target localisation (``--target``: the ``error_model`` of the fused estimate) and writes
the block (mysim_jax/tasks/perception_gap.py). ``compare`` checks that both evaluations
ran the same episodes and prints and writes both success rates (95 % Wilson intervals)
and their paired difference (Newcombe's interval). Bad input is a one-line error, exit 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    fit = sub.add_parser("fit", help="measured errors -> an env.perception block (YAML)")
    fit.add_argument("--uav", nargs="+", required=True, metavar="METRICS", help="perceive.py VIO metrics.json, per UAV")
    fit.add_argument("--target", required=True, metavar="METRICS", help="perceive.py target localisation metrics.json")
    fit.add_argument("--out", required=True, help="YAML file to write")
    fit.add_argument("--target-block", default="error_model",
                     choices=("error_model", "error_model_draws", "error_model_plain", "error_model_draws_plain"),
                     help="which fit of the target's metrics.json: the run's pose-noise draw (error_model, default) "
                     "or the draws of perceive.py --pose-seeds pooled (error_model_draws); the team's track filters "
                     "the self-calibrated fusion, the *_plain blocks the plain fusion's track")
    cmp_ = sub.add_parser("compare", help="the gap between two scripts/evaluate.py folders")
    cmp_.add_argument("true_dir", help="evaluation on true states")
    cmp_.add_argument("perceived_dir", help="the same episodes with --perception")
    cmp_.add_argument("--out", help="also write the result as JSON here")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    from mysim_jax.core.config_base import ConfigError
    from mysim_jax.tasks.perception_gap import GapError, compare_evaluations, perception_block, read_error_model

    try:
        if args.command == "fit":
            import yaml

            from mysim_jax.config.env import PerceptionConfig

            block = perception_block([read_error_model(p) for p in args.uav],
                                     read_error_model(args.target, key=args.target_block))
            PerceptionConfig(**block)                      # the block evaluate.py will read
            text = ("# env.perception: measured estimation errors as Gauss-Markov processes "
                    "(scripts/perception_gap.py fit)\n"
                    f"# from: {' '.join(args.uav)} and {args.target}\n" + yaml.safe_dump(block, sort_keys=False))
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(text)
            print(text, end="")
            return 0
        result = compare_evaluations(args.true_dir, args.perceived_dir)
    except (GapError, ConfigError) as err:
        return _error(str(err))
    t, p, g = result["true_states"], result["perceived_states"], result["gap"]
    print(f"{result['scene']}, {result['policy']}, {result['episodes']} episodes (seed {result['seed']}):\n"
          f"  true states:      {100 * t['rate']:.1f} % ({100 * t['interval95'][0]:.1f}-{100 * t['interval95'][1]:.1f})\n"
          f"  perceived states: {100 * p['rate']:.1f} % ({100 * p['interval95'][0]:.1f}-{100 * p['interval95'][1]:.1f})\n"
          f"  gap: {g['points']:+.1f} points ({g['interval95_points'][0]:+.1f} to {g['interval95_points'][1]:+.1f}, "
          f"paired); caught only on true states {g['caught_only_on_true']}, only on perceived "
          f"{g['caught_only_on_perceived']}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
