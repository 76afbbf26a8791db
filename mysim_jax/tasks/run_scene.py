"""Simulate one scene file and write its outputs (``scripts/simulate.py``).

Writes into a folder: ``trajectory.csv`` (:mod:`mysim_jax.io.trajectory` for the columns;
with controlled quadrotors also their references and motor speeds), ``config.yaml`` (the
resolved config), ``metrics.json`` (run time and summary numbers, the tracking errors of
controlled quadrotors, a capture scene's verdict), the kinematics plots of the scene's
``output.plot`` names, a capture scene's plots and animation, and ``replay.html`` (the
interactive 3D replay, :mod:`mysim_jax.io.replay`). Everything is written to a temporary
folder and moved into place when complete (:func:`mysim_jax.io.output.staged_output`); a
run that turns non-finite keeps its finite part and says so in ``metrics.json``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from mysim_jax.build import build
from mysim_jax.config.scene import SceneConfig, dump_config
from mysim_jax.io.output import staged_output
from mysim_jax.io.plots import plot_kinematics, plot_path
from mysim_jax.io.replay import write_replay_html
from mysim_jax.io.trajectory import trajectory_columns, write_trajectory_csv
from mysim_jax.driver import simulate
from mysim_jax.tasks.capture_plots import capture_report
from mysim_jax.tasks.scripted import team_policy
from mysim_jax.tuning.tracking import motor_columns, reference_columns, tracking_metrics


@dataclass
class SceneRun:
    """What :func:`simulate_scene` did: its ``metrics.json`` and how far it got."""

    name: str
    metrics: dict
    ok: bool
    failure: str | None
    reached: float        # s, the last saved time
    t_end: float          # s, the time asked for
    wall: float           # s, simulating (compile included)


def simulate_scene(config: SceneConfig, out: str | Path, progress: bool = True, replay: bool = True) -> SceneRun:
    """Build, simulate (a ``team:`` block or each quadrotor's reference flies the
    quadrotors) and write the outputs into ``out``. Raises ConfigError when the scene does
    not build (e.g. a step above the stability limit)."""
    scene, params, state = build(config)
    policy = team_policy(config, scene)
    run = config.run_settings()
    t0 = time.perf_counter()
    traj = simulate(scene, params, state, run, progress=progress, policy=policy)
    wall = time.perf_counter() - t0
    columns = trajectory_columns(scene, traj)
    columns.update(reference_columns(scene, params, traj.time))
    columns.update(motor_columns(scene, traj.controller))
    reached = float(traj.time[-1]) if len(traj.time) else 0.0
    metrics = {
        "scene": run.name, "status": "ok" if traj.ok else "failed", "integrator": scene.integrator,
        "precision": scene.precision, "dt": scene.dt, "substeps": scene.substeps, "t_end": reached,
        "n_outputs": int(len(traj.time)), "wall_time_s": wall,
        "final": {name: [float(columns[f"{name}_{a}"][-1]) for a in "xyz"] for name in run.plot if len(traj.time)},
    }
    with staged_output(out) as tmp:
        (tmp / "config.yaml").write_text(dump_config(config))
        write_trajectory_csv(tmp / "trajectory.csv", columns)
        metrics["plots"] = _plots(columns, run.plot, tmp) if len(traj.time) > 1 else []
        tracking = tracking_metrics(scene, columns) if len(traj.time) else {}
        if config.net is not None and config.target is not None and len(traj.time) > 1:
            metrics["capture"] = capture_report(columns, scene, params, config, tmp)
            metrics["plots"] += metrics["capture"]["plots"]
        if replay and len(traj.time):
            write_replay_html(columns, config, tmp / "replay.html")
        if not traj.ok:
            metrics["failure"] = traj.failure
        if tracking:
            metrics["tracking"] = tracking
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return SceneRun(name=run.name, metrics=metrics, ok=traj.ok, failure=traj.failure, reached=reached,
                    t_end=run.t_end, wall=wall)


def _plots(columns: dict, names, folder: Path) -> list[str]:
    """Kinematics plots of every name (and, for a quadrotor with a reference, its path)."""
    plots = []
    for name in names:
        reference = None
        if f"{name}_ref_x" in columns:
            reference = {"time": columns["time"], **{f"{name}_{a}": columns[f"{name}_ref_{a}"] for a in "xyz"}}
            plots.append(plot_path(columns, name, folder).name)
        plots += [p.name for p in plot_kinematics(columns, name, folder, reference=reference)]
    return plots


def summary_lines(result: SceneRun, out: str | Path, replay: bool = True) -> list[str]:
    """What a finished run prints: where its outputs are, a capture verdict, tracking errors."""
    m = result.metrics
    lines = [f"{result.name}: simulated {result.reached:g} s with {m['integrator']} ({m['precision']}) "
             f"in {result.wall:.2f} s (compile included); wrote {out}/trajectory.csv"
             + ("" if not replay else f", {out}/replay.html (open it in a browser)")
             + f" and {len(m['plots'])} plots"]
    if "capture" in m:
        c = m["capture"]
        verdict = (f"caught: held in the net from t = {c['held_from_s']:g} s to the end" if c["caught"]
                   else "not caught: " + ", ".join(k.replace("_", " ") + (" yes" if v else " no")
                                                  for k, v in c["at_end"].items()) + " at the end")
        lines.append(f"  target {verdict}; minimum UAV-target distance {c['min_uav_target_distance_m']:.3g} m, "
                     f"peak tether tension {c['peak_tether_tension_n']:.3g} N")
    for name, t in m.get("tracking", {}).items():
        lines.append(f"  {name}: RMS position error {t['rms_position_error_m']:.4g} m, "
                     f"max {t['max_position_error_m']:.4g} m")
    return lines
