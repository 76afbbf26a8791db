"""The control stage of ``step``: controller → motors → what the actuators apply.

``actuate(scene, params, state, control)`` runs once per environment step, before the
integrator: the scene's controller (or, with ``control`` given, the caller's commanded
motor speeds ``(n_quads, 4)`` rad/s) gives the motor commands; the motor model turns
them into the step mean of ``ω²``; wind and gimbal commands are sampled at the step's
start (on the controller's clock, :func:`~mysim_jax.control.pid.control_time`). All of
it is held over the step's sub-steps (zero-order hold).
"""

from __future__ import annotations

import jax.numpy as jnp

from mysim_jax.control.pid import CONTROLLERS, control_time
from mysim_jax.dynamics.gimbal import gimbal_command
from mysim_jax.dynamics.quadrotor import ActuatorInputs, motor_response, wind_force


def actuate(scene, params, state, control=None):
    """Returns ``(ActuatorInputs, ControlState)`` for one environment step."""
    qs, qp = scene.quadrotor, params.quadrotor
    memory = state.controller
    if control is None:
        if qs.controller == "none":
            raise ValueError(
                f"scene '{scene.name}' has quadrotors without a controller: pass the motor "
                "commands (n_quads, 4) rad/s as step(..., control=...)"
            )
        omega_cmd, memory = CONTROLLERS[qs.controller].command(scene, params, state)
    else:
        omega_cmd = jnp.asarray(control, dtype=state.phys.body_pos.dtype)
    dt = jnp.asarray(scene.dt, dtype=state.phys.body_pos.dtype)
    omega_end, speed_sq = motor_response(omega_cmd, memory.motor_speed, qp, dt, qs.has_motor_lag)
    t = control_time(scene, state.controller)
    memory = memory.replace(motor_speed=omega_end, steps=memory.steps + 1,
                            motor_command=jnp.clip(omega_cmd, qp.omega_min[:, None], qp.omega_max[:, None]))
    n_q = qs.n_quads
    dtype = speed_sq.dtype
    wind = wind_force(qp, t) if qs.has_wind else jnp.zeros((n_q, 3), dtype=dtype)
    gimbal = gimbal_command(qp, t) if qs.n_gimbals else jnp.zeros((0, 2), dtype=dtype)
    return ActuatorInputs(rotor_speed_sq=speed_sq, wind_force=wind, gimbal_command=gimbal), memory
