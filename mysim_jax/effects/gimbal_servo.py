"""The gimbal cameras' PD servos (an effect, see docs/effects.md).

A gimbal camera is a body on a universal joint (:mod:`mysim_jax.dynamics.gimbal` gives
its two angles and their rates from the bodies' state; the joint itself is an ordinary
constraint). Its servo is a force element: motor torques

    τ_k = kp_k wrap(a_k,cmd − a_k) − kd_k ȧ_k

act on the camera as ``τ₁ z_I + τ₂ z_J`` and on the UAV as the opposite, every sub-step.
The commands ``angle + amplitude sin(2π t / period)`` per axis
(``quadrotors.<i>.cameras.<j>.command``, :class:`~mysim_jax.config.quadrotor.GimbalCommand`)
are sampled once per environment step, at its start on the controller's clock, and held
over the step. The servo keeps no memory: its angles are the bodies'.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.control.pid import control_time
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads
from mysim_jax.dynamics.gimbal import gimbal_frames, gimbal_state
from mysim_jax.dynamics.quaternion import quat_rotate_inv


@dataclass(frozen=True)
class GimbalServoScene:
    marker_i: tuple[int, ...]        # (n_gimbals,) UAV-side marker (z axis = outer axis)
    marker_j: tuple[int, ...]        # (n_gimbals,) camera-side marker (z axis = inner axis)


@struct.dataclass
class GimbalServoParams:
    """Traced servo gains and commands of every gimbal (``params`` of :data:`GIMBAL_SERVO`)."""

    kp: jnp.ndarray                  # (n_gimbals, 2) N m/rad
    kd: jnp.ndarray                  # (n_gimbals, 2) N m s/rad
    angle: jnp.ndarray               # (n_gimbals, 2) rad, commanded mean angle
    amplitude: jnp.ndarray           # (n_gimbals, 2) rad
    period: jnp.ndarray              # (n_gimbals, 2) s


def gimbal_command(sp: GimbalServoParams, t):
    """Commanded angles ``(n_gimbals, 2)`` at time ``t``."""
    return sp.angle + sp.amplitude * jnp.sin(2.0 * jnp.pi * t / sp.period)


def gimbal_angles(scene, params, phys):
    """Angles ``(n_gimbals, 2)`` and angle rates ``(n_gimbals, 2)`` of the scene's gimbals."""
    static = GIMBAL_SERVO.static(scene)
    return gimbal_state(scene, params, phys, static.marker_i, static.marker_j)


def _stage(scene, params, phys, nodes, held) -> Loads:
    """The PD servo torques of all gimbals (body frames), towards the held commands."""
    static, sp = GIMBAL_SERVO.static(scene), GIMBAL_SERVO.params(params)
    bi, bj, rot_i, rot_j = gimbal_frames(scene, params, phys, static.marker_i, static.marker_j)
    angles, rates = gimbal_state(scene, params, phys, static.marker_i, static.marker_j)
    err = held - angles
    err = jnp.arctan2(jnp.sin(err), jnp.cos(err))          # shortest way round
    tau = sp.kp * err - sp.kd * rates                       # (n_gimbals, 2)
    tau_world = tau[:, :1] * rot_i[..., 2] + tau[:, 1:] * rot_j[..., 2]
    on_camera = quat_rotate_inv(phys.body_quat[bj], tau_world)
    on_uav = -quat_rotate_inv(phys.body_quat[bi], tau_world)
    torque = jnp.zeros((scene.n_bodies, 3), dtype=tau.dtype)
    torque = torque.at[bj].add(on_camera).at[bi].add(on_uav)
    return Loads(node_force=jnp.zeros((scene.n_nodes, 3), dtype=tau.dtype),
                 body_force=jnp.zeros((scene.n_bodies, 3), dtype=tau.dtype), body_torque=torque)


class _GimbalServo(Effect[GimbalServoScene, GimbalServoParams, None]):
    name = "gimbal_servo"

    def build(self, config, ctx):
        gimbals = [(q, c) for q in config.quadrotors for c in q.cameras if c.mount == "gimbal"]
        if not gimbals:
            return None

        def arr(x):
            return jnp.asarray(np.asarray(x, dtype=float).reshape(-1, 2), dtype=ctx.dtype)

        static = GimbalServoScene(marker_i=tuple(ctx.marker_names.index(f"{q.body}.{c.name}_mount") for q, c in gimbals),
                                  marker_j=tuple(ctx.marker_names.index(f"{c.name}.mount") for _, c in gimbals))
        params = GimbalServoParams(kp=arr([c.servo.kp for _, c in gimbals]), kd=arr([c.servo.kd for _, c in gimbals]),
                                   angle=arr([c.command.angle for _, c in gimbals]),
                                   amplitude=arr([c.command.amplitude for _, c in gimbals]),
                                   period=arr([c.command.period for _, c in gimbals]))
        return static, params, None

    def update(self, scene, params, state):
        """The commanded angles held over the step, at its start on the controller's clock."""
        return gimbal_command(self.params(params), control_time(scene, state.controller)), None

    def stages(self, static):
        return (("gimbal_servo", _stage),)


GIMBAL_SERVO = _GimbalServo()
