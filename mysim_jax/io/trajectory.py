"""Trajectory CSV: the simulator's output file and the export for rendering tools.

One header row, then one row per output time. Columns::

    time,
    for every point:  NAME_x NAME_y NAME_z NAME_vx NAME_vy NAME_vz NAME_ax NAME_ay NAME_az
    for every body:   NAME_x NAME_y NAME_z NAME_qw NAME_qx NAME_qy NAME_qz
                      NAME_vx NAME_vy NAME_vz NAME_ax NAME_ay NAME_az NAME_wx NAME_wy NAME_wz

and, for an evading target with entanglement (:mod:`mysim_jax.effects.entanglement`), the
column ``TARGET_entanglement`` (the share of its propulsion lost, 0 to 1).

Positions and velocities are world-frame (m, m/s), accelerations world-frame (m/s²),
quaternions scalar-first body → world, angular velocity ``w*`` body-frame (rad/s). Blender
or any other renderer needs only ``time``, ``NAME_x/y/z`` and ``NAME_qw..qz`` (paper
Alg. blender_rendering).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mysim_jax.core.types import Scene
from mysim_jax.effects.entanglement import ENTANGLEMENT
from mysim_jax.effects.target import TARGET
from mysim_jax.core.types import Trajectory

_XYZ = ("x", "y", "z")


def trajectory_columns(scene: Scene, traj: Trajectory) -> dict[str, np.ndarray]:
    """Ordered mapping column name -> ``(n_out,)`` values."""
    cols: dict[str, np.ndarray] = {"time": np.asarray(traj.time)}
    for i, name in enumerate(scene.point_names):
        for key, arr in (("", traj.phys.point_pos), ("v", traj.phys.point_vel), ("a", traj.acc.point_acc)):
            for c, axis in enumerate(_XYZ):
                cols[f"{name}_{key}{axis}"] = np.asarray(arr[:, i, c])
    for i, name in enumerate(scene.body_names):
        for c, axis in enumerate(_XYZ):
            cols[f"{name}_{axis}"] = np.asarray(traj.phys.body_pos[:, i, c])
        for c, axis in enumerate(("w", "x", "y", "z")):
            cols[f"{name}_q{axis}"] = np.asarray(traj.phys.body_quat[:, i, c])
        for key, arr in (("v", traj.phys.body_vel), ("a", traj.acc.body_acc), ("w", traj.phys.body_angvel)):
            for c, axis in enumerate(_XYZ):
                cols[f"{name}_{key}{axis}"] = np.asarray(arr[:, i, c])
    entanglement = ENTANGLEMENT.memory_or_none(traj)
    if entanglement is not None and TARGET.in_scene(scene):
        cols[f"{scene.body_names[TARGET.static(scene).body]}_entanglement"] = np.asarray(entanglement.level)
    return cols


def write_trajectory_csv(path: str | Path, columns: dict[str, np.ndarray]) -> None:
    """Write columns (all the same length) as CSV with a header row."""
    names = list(columns)
    data = np.column_stack([columns[n] for n in names])
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt="%.12g")


def read_trajectory_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a trajectory CSV back into a column mapping."""
    with open(path) as fh:
        header = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {name: data[:, i] for i, name in enumerate(header)}
