#!/usr/bin/env python
"""Train a capture team with MAPPO.

    python scripts/train.py configs/train_capture_falling.yaml
    python scripts/train.py configs/train_capture_falling.yaml --profile scratch   # no cloning
    python scripts/train.py CONFIG --set algo.lr=1e-3 --set run.seed=2 --out runs/mine
    python scripts/train.py --resume runs/mine          # continue a stopped run
    python scripts/train.py configs/train_capture_falling.yaml --seeds 3   # 3 seeds, one program

CONFIG is a training file with ``env:`` (a capture scene file and its overrides, or a
builtin toy task), ``algo:`` (MAPPO's settings) and ``run:`` (seed, checkpoints,
evaluation) sections (mysim_jax/mappo/config.py). ``--profile NAME`` applies the file's
named set of overrides (its ``profiles:``), then ``--set`` overrides single values.

While it runs, a progress bar shows the mean return and success rate of the episodes that
ended in the last iteration and the team steps/s (rollout and update). Training stops
after algo.total_env_steps team steps (a step budget; run.time_limit_min is an optional
guard, and a run it stops says so in summary.json and curves.png). It writes into OUT
(default ``runs/<name>``; mysim_jax/mappo/run.py): ``metrics.csv`` and TensorBoard events
(``tb/``), ``curves.png``, orbax checkpoints every ``run.checkpoint_every`` iterations,
the final policy (``policy/``, usable as ``scripts/evaluate.py --policy OUT/policy``),
and at the end the evaluation report of ``scripts/evaluate.py`` (``eval/``) on
``run.eval_episodes`` episodes, and ``summary.json``.

``--seeds N`` (``run.seeds``) trains the seeds ``run.seed`` to ``run.seed + N - 1`` side by
side in one program (vmapped): each seed's files go to ``OUT/seed_<seed>/``, and
``OUT/seeds.md`` tables them (mean, spread and each seed).

``--resume OUT`` continues from OUT's last complete checkpoint (a run killed at any
moment loses at most one checkpoint interval) and finishes as the uninterrupted run would.

A training file with ``run.then: FILE`` is a chain (mysim_jax/mappo/chain.py): when its run
has ended, FILE (``algo.init: policy``) trains from the run's policy into ``OUT/then/``;
the chain's team is ``OUT/then/policy``, and ``--resume OUT`` continues whichever run it
stopped in. ``--set run.seed=N`` is the seed of both runs; ``--set then.KEY=VALUE`` sets a
value of FILE (``then.run.eval_baseline=false``).

The environments are split over every device JAX sees (``run.devices``). Several
processes (hosts) train one run together when each is started with the same arguments and
``--coordinator HOST:PORT --num-processes N --process-id I`` (``jax.distributed``; OUT on a
folder they all see): process 0 writes the run folder and the evaluation, every process
computes.

Every input is checked before anything compiles; a problem is a one-line error naming
the field, exit code 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys

from mysim_jax.core.cli import add_set_argument


def _error(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="YAML training file")
    add_set_argument(parser, "algo.lr=1e-3", "a training-file value")
    parser.add_argument("--profile", default=None, metavar="NAME",
                        help="apply the training file's profile NAME (its profiles: block) before --set")
    parser.add_argument("--seeds", type=int, default=None, metavar="N",
                        help="train N seeds (run.seed, run.seed + 1, ...) in one program (sets run.seeds)")
    parser.add_argument("--out", default=None, help="run folder to create (default runs/<name>)")
    parser.add_argument("--resume", default=None, metavar="RUN_DIR", help="continue the run in RUN_DIR")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    parser.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    group = parser.add_argument_group("several processes (jax.distributed): give all three, the same "
                                      "--coordinator and --num-processes in every process")
    group.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0's coordination service")
    group.add_argument("--num-processes", type=int, metavar="N", help="number of processes")
    group.add_argument("--process-id", type=int, metavar="I", help="this process's index, 0 to N-1")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    distributed = (args.coordinator, args.num_processes, args.process_id)
    if any(v is not None for v in distributed) and any(v is None for v in distributed):
        return _error("--coordinator, --num-processes and --process-id go together: give all three or none")
    if args.num_processes is not None and not (args.num_processes >= 1 and 0 <= args.process_id < args.num_processes):
        return _error(f"--process-id {args.process_id} with --num-processes {args.num_processes}: the id must be "
                      "0 to N-1 and N at least 1")

    from mysim_jax.config.overrides import override_list
    from mysim_jax.core.config_base import ConfigError
    from mysim_jax.io.output import OutputError
    from mysim_jax.mappo.chain import train_chain
    from mysim_jax.mappo.run import describe_run, prepare

    if args.resume is not None and (args.config is not None or args.out is not None or args.profile is not None
                                    or args.seeds is not None):
        return _error("--resume RUN_DIR takes no training file, --out, --profile or --seeds (the run folder holds "
                      "them)")
    if args.seeds is not None and args.seeds < 1:
        return _error(f"--seeds {args.seeds}: give at least 1")
    overrides = override_list(args.overrides, then={"run.seeds": args.seeds})
    try:
        prepared = prepare(args.config, overrides, args.out, args.resume, args.profile)
    except (ConfigError, OutputError) as err:
        return _error(str(err))
    if args.coordinator is not None:
        import jax

        # after every process has checked its input (nothing written yet), before any JAX work
        jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=args.num_processes,
                                   process_id=args.process_id)
    if args.process_id in (None, 0):
        print(describe_run(prepared))
    from mysim_jax.mappo.checkpoint import CheckpointError

    try:
        summaries = train_chain(prepared, progress=not args.no_progress, evaluate=not args.no_eval)
    except (CheckpointError, ConfigError) as err:
        return _error(str(err))
    for summary in summaries:
        if summary:            # the first (or only) process
            print(json.dumps({k: v for k, v in summary.items() if k != "evaluation"}, indent=None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
