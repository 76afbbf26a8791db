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
applies a gains file written by ``scripts/tune_pid.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML scene file")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set sim.dt=5e-4 (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--gains", metavar="FILE", help="controller gains for the quadrotors (YAML, e.g. the "
                        "gains.yaml of scripts/tune_pid.py); --set overrides still apply on top")
    args = parser.parse_args(argv)

    from mysim_jax.config import ConfigError, dump_config, load_config

    try:
        overrides = list(args.overrides)
        if args.gains:
            from mysim_jax.control.config import gain_overrides

            overrides = gain_overrides(args.gains, args.config) + overrides
        config = load_config(args.config, overrides)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    import jax

    if config.sim.precision == "float64":
        jax.config.update("jax_enable_x64", True)

    from mysim_jax.build import build
    from mysim_jax.control.tracking import motor_columns, reference_columns, tracking_metrics
    from mysim_jax.io.plots import plot_kinematics, plot_path
    from mysim_jax.io.trajectory import trajectory_columns, write_trajectory_csv
    from mysim_jax.sim import simulate

    try:
        scene, params, state = build(config)
    except ConfigError as err:
        print(f"error: {args.config}: {err}", file=sys.stderr)
        return 2

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(dump_config(config))

    t0 = time.perf_counter()
    traj = simulate(scene, params, state, progress=not args.no_progress)
    wall = time.perf_counter() - t0

    columns = trajectory_columns(scene, traj)
    columns.update(reference_columns(scene, params, traj.time))
    columns.update(motor_columns(scene, traj.controller))
    write_trajectory_csv(out / "trajectory.csv", columns)
    plots = []
    for name in scene.plot_names:
        reference = None
        if f"{name}_ref_x" in columns:
            reference = {"time": columns["time"], **{f"{name}_{a}": columns[f"{name}_ref_{a}"] for a in "xyz"}}
            plots.append(plot_path(columns, name, out).name)
        plots += [p.name for p in plot_kinematics(columns, name, out, reference=reference)]
    tracking = tracking_metrics(scene, columns)

    metrics = {
        "scene": scene.name,
        "integrator": scene.integrator,
        "precision": scene.precision,
        "dt": scene.dt,
        "substeps": scene.substeps,
        "t_end": float(traj.time[-1]),
        "n_outputs": int(len(traj.time)),
        "wall_time_s": wall,
        "final": {name: [float(columns[f"{name}_{a}"][-1]) for a in "xyz"] for name in scene.plot_names},
        "plots": plots,
    }
    if tracking:
        metrics["tracking"] = tracking
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    print(f"{scene.name}: simulated {traj.time[-1]:g} s with {scene.integrator} ({scene.precision}) "
          f"in {wall:.2f} s (compile included); wrote {out}/trajectory.csv and {len(plots)} plots")
    for name, m in tracking.items():
        print(f"  {name}: RMS position error {m['rms_position_error_m']:.4g} m, "
              f"max {m['max_position_error_m']:.4g} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
