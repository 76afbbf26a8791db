"""Tracking errors of controlled quadrotors against their references (host side and
traced), shared by ``scripts/simulate.py``, ``scripts/tune_pid.py`` and the tests.

The reference is evaluated on the controller's clock (``steps · dt``,
:func:`mysim_jax.control.pid.control_time`), which equals the output grid time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.control.pid import control_time
from mysim_jax.control.reference import reference
from mysim_jax.driver import output_times, steps_per_output
from mysim_jax.sim import rollout


def reference_along(params, times):
    """References of all quadrotors at ``times`` ``(n,)``: a Reference with leaves ``(n, n_quads, …)``."""
    if params.controller is None or params.controller.reference is None:
        raise ValueError("the scene has no reference trajectory (quadrotors.i.reference) to measure tracking "
                         "errors against")
    return jax.vmap(lambda t: reference(params.controller.reference, t))(jnp.asarray(times))


def position_errors(scene, params, states):
    """``body_pos − r_d`` ``(n, n_quads, 3)`` along stacked states (traced; differentiable)."""
    body = np.asarray(scene.quadrotor.body, dtype=np.int32)
    ref = reference_along(params, control_time(scene, states.controller))
    return states.phys.body_pos[:, body] - ref.pos


def reference_columns(scene, params, times) -> dict[str, np.ndarray]:
    """``NAME_ref_x/y/z`` (m) and ``NAME_ref_yaw`` (rad) for every controlled quadrotor."""
    if scene.quadrotor is None or params.controller is None or params.controller.reference is None:
        return {}
    ref = jax.tree.map(np.asarray, reference_along(params, times))
    cols = {}
    for q, b in enumerate(scene.quadrotor.body):
        name = scene.body_names[b]
        for c, axis in enumerate("xyz"):
            cols[f"{name}_ref_{axis}"] = ref.pos[:, q, c]
        cols[f"{name}_ref_yaw"] = ref.yaw[:, q]
    return cols


def motor_columns(scene, memory) -> dict[str, np.ndarray]:
    """``NAME_rotorK`` (K = 1..4): commanded (clipped) motor speed held from each saved time, rad/s."""
    if scene.quadrotor is None or memory is None:
        return {}
    cols = {}
    for q, b in enumerate(scene.quadrotor.body):
        for k in range(4):
            cols[f"{scene.body_names[b]}_rotor{k + 1}"] = np.asarray(memory.motor_command[:, q, k])
    return cols


def tracking_metrics(scene, columns) -> dict[str, dict]:
    """RMS and max position error (m) of every controlled quadrotor from trajectory columns."""
    out = {}
    if scene.quadrotor is None:
        return out
    for b in scene.quadrotor.body:
        name = scene.body_names[b]
        if f"{name}_ref_x" not in columns:
            continue
        err = np.stack([columns[f"{name}_{a}"] - columns[f"{name}_ref_{a}"] for a in "xyz"], axis=-1)
        norm = np.linalg.norm(err, axis=-1)
        out[name] = {
            "rms_position_error_m": float(np.sqrt(np.mean(norm ** 2))),
            "max_position_error_m": float(norm.max()),
            "rms_error_xyz_m": [float(v) for v in np.sqrt(np.mean(err ** 2, axis=0))],
        }
    return out


def _grid_rollout(scene, params, state, n_out: int, every: int):
    _, states = rollout(scene, params, state, n_out * every, every)
    first = jax.tree.map(lambda a: a[None], state)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=0), first, states)


_grid_rollout_jit = jax.jit(_grid_rollout, static_argnums=(0, 3, 4))


def evaluate_tracking(scene, params, state, run) -> dict[str, dict]:
    """Run the scene to ``run.t_end`` and return :func:`tracking_metrics` on the output grid
    of ``run`` (:class:`~mysim_jax.config.scene.RunSettings`; the numbers ``scripts/simulate.py``
    writes). Compiled once per scene: calls with other Params (gains) reuse it."""
    times = output_times(run)
    every = steps_per_output(scene, run)
    states = _grid_rollout_jit(scene, params, state, len(times) - 1, every)
    body = np.asarray(scene.quadrotor.body)
    pos = np.asarray(states.phys.body_pos)[:, body]
    ref = reference_columns(scene, params, times)
    columns = {"time": times}
    for q, b in enumerate(scene.quadrotor.body):
        name = scene.body_names[b]
        for c, axis in enumerate("xyz"):
            columns[f"{name}_{axis}"] = pos[:, q, c]
    columns.update(ref)
    return tracking_metrics(scene, columns)
