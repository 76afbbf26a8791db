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
import json
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML scene file")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set sim.dt=5e-4 (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--no-replay", action="store_true", help="do not write replay.html (the interactive 3D "
                        "replay of the run)")
    parser.add_argument("--gains", metavar="FILE", help="controller gains for the quadrotors (YAML, e.g. the "
                        "gains.yaml of scripts/tune_pid.py); --set overrides still apply on top")
    args = parser.parse_args(argv)

    from mysim_jax.config.scene import ConfigError, check_output_memory, dump_config, load_config
    from mysim_jax.io.output import OutputError, check_output_dir

    try:
        overrides = list(args.overrides)
        if args.gains is not None:
            from mysim_jax.config.quadrotor import gain_overrides

            overrides = gain_overrides(args.gains, args.config) + overrides
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

    import jax

    if config.sim.precision == "float64":
        jax.config.update("jax_enable_x64", True)

    from mysim_jax.build import build
    from mysim_jax.tuning.tracking import motor_columns, reference_columns, tracking_metrics
    from mysim_jax.io.output import staged_output
    from mysim_jax.io.plots import plot_kinematics, plot_path
    from mysim_jax.io.replay import write_replay_html
    from mysim_jax.io.trajectory import trajectory_columns, write_trajectory_csv
    from mysim_jax.sim import simulate

    try:
        scene, params, state = build(config)
    except ConfigError as err:
        print(f"error: {args.config}: {err}", file=sys.stderr)
        return 2

    from mysim_jax.tasks.capture_plots import capture_report
    from mysim_jax.tasks.scripted import team_policy

    policy = team_policy(config, scene)
    t0 = time.perf_counter()
    run = config.run_settings()
    traj = simulate(scene, params, state, run, progress=not args.no_progress, policy=policy)
    wall = time.perf_counter() - t0

    columns = trajectory_columns(scene, traj)
    columns.update(reference_columns(scene, params, traj.time))
    columns.update(motor_columns(scene, traj.controller))
    reached = float(traj.time[-1]) if len(traj.time) else 0.0
    with staged_output(out) as tmp:
        (tmp / "config.yaml").write_text(dump_config(config))
        write_trajectory_csv(tmp / "trajectory.csv", columns)
        plots = []
        if len(traj.time) > 1:
            for name in run.plot:
                reference = None
                if f"{name}_ref_x" in columns:
                    reference = {"time": columns["time"], **{f"{name}_{a}": columns[f"{name}_ref_{a}"] for a in "xyz"}}
                    plots.append(plot_path(columns, name, tmp).name)
                plots += [p.name for p in plot_kinematics(columns, name, tmp, reference=reference)]
        tracking = tracking_metrics(scene, columns) if len(traj.time) else {}
        metrics = {
            "scene": run.name,
            "status": "ok" if traj.ok else "failed",
            "integrator": scene.integrator,
            "precision": scene.precision,
            "dt": scene.dt,
            "substeps": scene.substeps,
            "t_end": reached,
            "n_outputs": int(len(traj.time)),
            "wall_time_s": wall,
            "final": {name: [float(columns[f"{name}_{a}"][-1]) for a in "xyz"]
                      for name in run.plot if len(traj.time)},
            "plots": plots,
        }
        if config.net is not None and config.target is not None and len(traj.time) > 1:
            capture = capture_report(columns, scene, params, config, tmp)
            metrics["capture"] = capture
            plots += capture["plots"]
        if not args.no_replay and len(traj.time):
            write_replay_html(columns, config, tmp / "replay.html")
        if not traj.ok:
            metrics["failure"] = traj.failure
        if tracking:
            metrics["tracking"] = tracking
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if not traj.ok:
        print(f"error: {args.config}: {traj.failure}", file=sys.stderr)
        print(f"{run.name}: stopped at t = {reached:g} s of {run.t_end:g} s; wrote the finite part to "
              f"{out}/ (metrics.json status: failed)", file=sys.stderr)
        return 3
    print(f"{run.name}: simulated {reached:g} s with {scene.integrator} ({scene.precision}) "
          f"in {wall:.2f} s (compile included); wrote {out}/trajectory.csv"
          + ("" if args.no_replay else f", {out}/replay.html (open it in a browser)") + f" and {len(plots)} plots")
    if "capture" in metrics:
        c = metrics["capture"]
        verdict = (f"caught: held in the net from t = {c['held_from_s']:g} s to the end" if c["caught"]
                   else "not caught: " + ", ".join(k.replace("_", " ") + (" yes" if v else " no")
                                                  for k, v in c["at_end"].items()) + " at the end")
        print(f"  target {verdict}; minimum UAV-target distance {c['min_uav_target_distance_m']:.3g} m, "
              f"peak tether tension {c['peak_tether_tension_n']:.3g} N")
    for name, m in tracking.items():
        print(f"  {name}: RMS position error {m['rms_position_error_m']:.4g} m, "
              f"max {m['max_position_error_m']:.4g} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
