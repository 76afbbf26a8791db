#!/usr/bin/env python
"""Train a capture team with MAPPO.

    python scripts/train.py configs/train_capture_falling.yaml
    python scripts/train.py configs/train_capture_falling.yaml --profile scratch   # no cloning
    python scripts/train.py CONFIG --set algo.lr=1e-3 --set run.seed=2 --out runs/mine
    python scripts/train.py --resume runs/mine          # continue a stopped run

CONFIG is a training file with ``env:`` (a capture scene file and its overrides, or a
builtin toy task), ``algo:`` (MAPPO's settings) and ``run:`` (seed, checkpoints,
evaluation) sections (mysim_jax/mappo/config.py). ``--profile NAME`` applies the file's
named set of overrides (its ``profiles:``), then ``--set`` overrides single values.

While it runs, a progress bar shows the mean return and success rate of the episodes that
ended in the last iteration and the env-steps/s (update included). It writes into OUT
(default ``runs/<name>``; mysim_jax/mappo/run.py): ``metrics.csv`` and TensorBoard events
(``tb/``), ``curves.png``, orbax checkpoints every ``run.checkpoint_every`` iterations,
the final policy (``policy/``, usable as ``scripts/evaluate.py --policy OUT/policy``),
and at the end the evaluation report of ``scripts/evaluate.py`` (``eval/``) on
``run.eval_episodes`` episodes, and ``summary.json``.

``--resume OUT`` continues from OUT's last complete checkpoint (a run killed at any
moment loses at most one checkpoint interval) and finishes as the uninterrupted run would.

Every input is checked before anything compiles; a problem is a one-line error naming
the field, exit code 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="YAML training file")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a training-file value, e.g. --set algo.lr=1e-3 (repeatable)")
    parser.add_argument("--profile", default=None, metavar="NAME",
                        help="apply the training file's profile NAME (its profiles: block) before --set")
    parser.add_argument("--out", default=None, help="run folder to create (default runs/<name>)")
    parser.add_argument("--resume", default=None, metavar="RUN_DIR", help="continue the run in RUN_DIR")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    parser.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    args = parser.parse_args(argv)

    from mysim_jax.config_base import ConfigError
    from mysim_jax.io.output import OutputError
    from mysim_jax.mappo.run import describe_run, prepare, train_run

    if args.resume is not None and (args.config is not None or args.out is not None or args.profile is not None):
        return _error("--resume RUN_DIR takes no training file, --out or --profile (the run folder holds them)")
    try:
        prepared = prepare(args.config, args.overrides, args.out, args.resume, args.profile)
    except (ConfigError, OutputError) as err:
        return _error(str(err))
    print(describe_run(prepared))
    from mysim_jax.mappo.checkpoint import CheckpointError

    try:
        summary = train_run(prepared, progress=not args.no_progress, evaluate=not args.no_eval)
    except (CheckpointError, ConfigError) as err:
        return _error(str(err))
    print(json.dumps({k: v for k, v in summary.items() if k != "evaluation"}, indent=None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
