"""The control stage of ``step``: controller → motors → what the actuators apply.

``actuate(scene, params, state, control)`` runs once per environment step, before the
integrator. ``control`` selects the source of the motor commands by its Python type,
when the step is traced (:mod:`mysim_jax.control.setpoint`):

* a :class:`~mysim_jax.control.setpoint.Setpoint` — the scene's controller tracks it,
  after :func:`~mysim_jax.control.setpoint.limit_setpoint` maps it into the flyable box
  and the speed limit;
* ``None`` — the controller tracks the scene's reference at the controller's clock
  (:func:`~mysim_jax.control.pid.control_time`), limited the same way;
* anything else — the caller's commanded motor speeds ``(n_quads, 4)`` rad/s.

The motor model turns the command into the step mean of ``ω²``, held over the step's
sub-steps (zero-order hold). Wind and the gimbals' commands are effects with updates of
their own (:mod:`mysim_jax.effects.wind`, :mod:`mysim_jax.effects.gimbal_servo`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mysim_jax.control.pid import CONTROLLERS, control_time
from mysim_jax.control.setpoint import Setpoint, as_setpoint, brake_descent, limit_setpoint, reference_setpoint
from mysim_jax.dynamics.quadrotor import ActuatorInputs, motor_response


def _setpoint(scene, params, state, control):
    """The limited setpoint the controller tracks this step (``control``: Setpoint or None)."""
    qs, cp = scene.quadrotor, params.controller
    dtype = state.phys.body_pos.dtype
    if control is None:
        if cp.reference is None:
            raise ValueError(
                "the scene has controlled quadrotors without a reference trajectory: pass "
                "setpoints as step(..., control=Setpoint(...)) (mysim_jax.control.setpoint), or give "
                "every quadrotor a reference (quadrotors.i.reference)"
            )
        setpoint = reference_setpoint(params, control_time(scene, state.controller))
    else:
        setpoint = as_setpoint(control, qs.n_quads, dtype)
    position = state.phys.body_pos[np.asarray(qs.body, dtype=np.int32)]
    setpoint = limit_setpoint(setpoint, cp, qs.setpoint_mode, position)
    if qs.setpoint_mode == "velocity" and "braking" in qs.descent_limit:
        setpoint = brake_descent(setpoint, scene, params, position)
    return setpoint


def actuate(scene, params, state, control=None):
    """Returns ``(ActuatorInputs, ControlState)`` for one environment step."""
    qs, qp = scene.quadrotor, params.quadrotor
    memory = state.controller
    if control is None or isinstance(control, Setpoint):
        if qs.controller == "none":
            given = "" if control is None else " (a Setpoint needs one)"
            raise ValueError(
                f"the scene has quadrotors without a controller{given}: pass the motor commands "
                "(n_quads, 4) rad/s as step(..., control=...)"
            )
        setpoint = _setpoint(scene, params, state, control)
        omega_cmd, memory = CONTROLLERS[qs.controller].command(scene, params, state, setpoint)
    else:
        omega_cmd = jnp.asarray(control, dtype=state.phys.body_pos.dtype)
    dt = jnp.asarray(scene.dt, dtype=state.phys.body_pos.dtype)
    omega_end, speed_sq = motor_response(omega_cmd, memory.motor_speed, qp, dt, qs.has_motor_lag)
    memory = memory.replace(motor_speed=omega_end, steps=memory.steps + 1,
                            motor_command=jnp.clip(omega_cmd, qp.omega_min[:, None], qp.omega_max[:, None]))
    return ActuatorInputs(rotor_speed_sq=speed_sq), memory
