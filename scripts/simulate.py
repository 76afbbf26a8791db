#!/usr/bin/env python
"""Simulate one scene and write its outputs.

    python scripts/simulate.py configs/rope_net.yaml --out out/rope [--set sim.dt=5e-5 ...]
    python scripts/simulate.py configs/uav_track_large.yaml --out out/large --gains out/tune/gains.yaml

Writes into OUT: ``trajectory.csv`` (see mysim_jax/io/trajectory.py for the columns),
``config.yaml`` (the resolved config, overrides applied), ``metrics.json`` (run time and
summary numbers), and ``NAME_{position,velocity,acceleration}.png`` for every name in the
scene's ``output.plot`` list. Scenes with controlled quadrotors also get the reference
columns ``NAME_ref_x/y/z/yaw`` and motor columns ``NAME_rotor1..4`` in the CSV, the
reference drawn on the position plot, ``NAME_path.png`` (reference against actual path)
and the RMS / max tracking errors under ``tracking`` in ``metrics.json``. ``--gains``
applies a gains file written by ``scripts/tune_pid.py``. ``replay.html`` is an
interactive 3D replay of the run (time slider, play / pause; one self-contained file
that opens offline in a browser; mysim_jax/io/replay.py); ``--no-replay`` skips it.

Every input (config file, overrides, gains file, the OUT folder) is checked before
anything is compiled; a problem is a one-line error naming the file or field, exit code
2, and nothing is written. Outputs are written to a temporary folder and moved into OUT
only when complete. A run whose state turns non-finite (or whose adaptive solver gives
up) stops there: OUT then holds the finite part, ``metrics.json`` says
``"status": "failed"`` with the reason, the error names the time and the points or
bodies, and the exit code is 3.
"""

from __future__ import annotations

import argparse
import sys

from mysim_jax.core.cli import add_set_argument


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML scene file")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    add_set_argument(parser, "sim.dt=5e-4", "a config value")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--no-replay", action="store_true", help="do not write replay.html (the interactive 3D "
                        "replay of the run)")
    parser.add_argument("--gains", metavar="FILE", help="controller gains for the quadrotors (YAML, e.g. the "
                        "gains.yaml of scripts/tune_pid.py); --set overrides still apply on top")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    from mysim_jax.config.overrides import override_list
    from mysim_jax.config.scene import ConfigError, check_output_memory, load_config
    from mysim_jax.io.output import OutputError, check_output_dir

    try:
        overrides = list(args.overrides)
        if args.gains is not None:
            from mysim_jax.config.quadrotor import gain_overrides

            overrides = override_list(overrides, first=gain_overrides(args.gains, args.config))
        config = load_config(args.config, overrides)
        # a run without a team: block flies the quadrotors' references, so a controlled
        # quadrotor needs one (a scene without them is driven by setpoints passed to step)
        unflown = [i for i, q in enumerate(config.quadrotors) if q.controller is not None and q.reference is None]
        if unflown and config.team is None:
            raise ConfigError(f"{args.config}: quadrotors.{unflown[0]}.reference: missing; simulate.py flies each "
                              "controlled quadrotor along its reference, or a team: block flies them (a scene "
                              "without either is driven by setpoints passed to step() from Python)")
        check_output_memory(config, args.config)
        out = check_output_dir(args.out)
    except (ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.core.extras import available

    if not args.no_replay and not available("plotly"):
        print("note: replay.html skipped: the HTML replay needs plotly (pip install -e '.[plots]')", file=sys.stderr)
        args.no_replay = True

    from mysim_jax.core.precision import use_precision

    use_precision(config.sim.precision)

    from mysim_jax.tasks.run_scene import simulate_scene, summary_lines

    try:
        result = simulate_scene(config, out, progress=not args.no_progress, replay=not args.no_replay)
    except ConfigError as err:
        print(f"error: {args.config}: {err}", file=sys.stderr)
        return 2
    if not result.ok:
        print(f"error: {args.config}: {result.failure}", file=sys.stderr)
        print(f"{result.name}: stopped at t = {result.reached:g} s of {result.t_end:g} s; wrote the finite part to "
              f"{out}/ (metrics.json status: failed)", file=sys.stderr)
        return 3
    print("\n".join(summary_lines(result, out, replay=not args.no_replay)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
