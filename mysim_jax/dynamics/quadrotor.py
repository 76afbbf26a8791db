"""Quadrotor rotor forces, control allocation and motors (paper Sec. 2.2).

Geometry. Rotor ``i`` sits at ``d_i = l_i [sin θ_i, cos θ_i, 0]`` in the body frame
(from the centre of mass); the paper's angles ``π/4 + k π/2`` give an X layout with
rotor 1 front-right at ``(+, +)``, rotor 2 at ``(+, −)``, rotor 3 at ``(−, −)`` and
rotor 4 at ``(−, +)``.

Forces. Rotor ``i`` pushes ``c_i ω_i²`` along body z at ``d_i`` and reacts on the body
with ``spin_i k_i ω_i²`` about body z (``spin_i = +1``: the rotor turns clockwise seen
from above). The wrench on the body, ``w = (T, τ_x, τ_y, τ_z)`` (total thrust along
body z, torques about the body axes at the CoM), is linear in ``s = (ω_1², …, ω_4²)``::

    w = M s,   M[0, i] = c_i,   M[1, i] = c_i d_iy,   M[2, i] = −c_i d_ix,   M[3, i] = spin_i k_i

(``d_i × (0, 0, c_i ω_i²)`` gives the two arm torques). For the paper's layout
``τ_x = (√2/2) l c (ω1² − ω2² − ω3² + ω4²)`` is the paper's ``τ_θ``,
``τ_y = −(√2/2) l c (ω1² + ω2² − ω3² − ω4²)`` is minus the paper's ``τ_φ`` (the paper's
φ axis points along −y) and ``τ_z = k (ω1² − ω2² + ω3² − ω4²)`` is ``τ_ψ``. The paper's
``τ = Σ d̃_i σ_i + k_i σ_i`` writes the reaction torque as ``k_i`` times the thrust
vector; dimensionally (k in N m s²) it is ``k_i ω_i²`` about z, which is what is here.
``M`` is inverted exactly (``allocation_inverse``), so any non-singular layout works.

Motors. Commanded speeds are clipped to ``[ω_min, ω_max]``. With a time constant ``τ``
the motor speed follows ``ω̇ = (ω_cmd − ω)/τ``; over one environment step ``dt`` (the
command is held) this is integrated exactly, ``ω(t) = ω_cmd + (ω_0 − ω_cmd) e^{−t/τ}``,
and the rotors apply the exact step mean of ``ω(t)²`` (thrust and reaction torque are
linear in ``ω²``, so the impulse over the step is exact). Without lag they apply the
clipped command.

Aerodynamics (only when a scene asks) are effects of their own (docs/effects.md): linear
body drag (:mod:`mysim_jax.effects.body_drag`) and wind (:mod:`mysim_jax.effects.wind`);
so is the gimbal cameras' servo (:mod:`mysim_jax.effects.gimbal_servo`).

Rotor gyroscopic torques and blade flapping are neglected, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.dynamics.forces import Loads
from mysim_jax.dynamics.quaternion import quat_rotate


@dataclass(frozen=True)
class QuadrotorScene:
    """Static quadrotor structure of a scene (part of the hashable Scene)."""

    body: tuple[int, ...]                    # (n_quads,) body index of each quadrotor
    controller: str = "none"                 # "cascaded_pid" | "none" (motor commands from step's control)
    feedforward: tuple[str, ...] = ()        # (n_quads,) "none" | "acceleration" | "full"
    attitude_gain_units: tuple[str, ...] = ()  # (n_quads,) "rotor_speed_squared" | "torque"
    saturation: tuple[str, ...] = ()         # (n_quads,) "clip" | "attitude_priority": motor-limit handling
    thrust_limit: tuple[str, ...] = ()       # (n_quads,) "none" | "vertical_priority": thrust-vector limit
    descent_limit: tuple[str, ...] = ()      # (n_quads,) "none" | "braking": velocity-mode descent limit
    setpoint_mode: str = "position"          # "position" | "velocity": what the controller's setpoint fixes
    has_motor_lag: bool = False

    @property
    def n_quads(self) -> int:
        return len(self.body)


@struct.dataclass
class QuadrotorParams:
    """Traced physical parameters of the quadrotors' rotors and motors."""

    rotor_pos: jnp.ndarray            # (n_quads, 4, 3) m, body frame, from the CoM
    lift_coefficient: jnp.ndarray     # (n_quads, 4) N s^2/rad^2
    torque_coefficient: jnp.ndarray   # (n_quads, 4) N m s^2/rad^2
    spin: jnp.ndarray                 # (n_quads, 4) +1 / -1
    omega_min: jnp.ndarray            # (n_quads,) rad/s
    omega_max: jnp.ndarray            # (n_quads,) rad/s
    motor_time_constant: jnp.ndarray  # (n_quads,) s (1e-9 for motors without lag)


@struct.dataclass
class ActuatorInputs:
    """What the rotors apply over one environment step (held constant over it)."""

    rotor_speed_sq: jnp.ndarray   # (n_quads, 4) rad^2/s^2, step mean of ω_i²


# --- geometry and allocation -----------------------------------------------------------


def allocation_matrix(qp: QuadrotorParams):
    """``M`` ``(n_quads, 4, 4)``: ``(T, τ_x, τ_y, τ_z) = M (ω_1², …, ω_4²)``."""
    c = qp.lift_coefficient
    d = qp.rotor_pos
    return jnp.stack([c, c * d[..., 1], -c * d[..., 0], qp.spin * qp.torque_coefficient], axis=-2)


def top_thrust(qp: QuadrotorParams):
    """``(n_quads,)`` N: the rotors' total thrust at their present top speed ``Σ c_L ω_max²``
    (a motor fault lowers ``ω_max``)."""
    return jnp.sum(qp.lift_coefficient, axis=-1) * qp.omega_max ** 2


def allocation_inverse(qp: QuadrotorParams):
    """``M⁻¹`` ``(n_quads, 4, 4)``: squared motor speeds from thrust and torques."""
    return jnp.linalg.inv(allocation_matrix(qp))


def rotor_wrench(qp: QuadrotorParams, rotor_speed_sq):
    """Total thrust ``(n_quads,)`` (N, along body z) and body torque ``(n_quads, 3)`` (N m)."""
    w = jnp.einsum("qij,qj->qi", allocation_matrix(qp), rotor_speed_sq)
    return w[:, 0], w[:, 1:]


# --- motors -------------------------------------------------------------------------------


def motor_response(omega_cmd, omega_prev, qp: QuadrotorParams, dt, has_lag: bool):
    """Clip the command and run the motors over one step of length ``dt``.

    Returns ``(omega_end (n_quads, 4), mean_speed_sq (n_quads, 4))``: the motor speed at
    the end of the step and the step mean of ``ω²`` that the rotors apply.
    """
    lo, hi = qp.omega_min[:, None], qp.omega_max[:, None]
    cmd = jnp.clip(omega_cmd, lo, hi)
    if not has_lag:
        return cmd, cmd * cmd
    with jax.named_scope("motor_lag"):
        tau = qp.motor_time_constant[:, None]
        decay = jnp.exp(-dt / tau)
        b = omega_prev - cmd
        omega_end = cmd + b * decay
        ratio = tau / dt
        mean_sq = cmd * cmd + 2.0 * cmd * b * ratio * (1.0 - decay) + b * b * (0.5 * ratio) * (1.0 - decay * decay)
    return omega_end, mean_sq


# --- force stages -----------------------------------------------------------------------------


def _on_bodies(scene, values, index):
    zeros = jnp.zeros((scene.n_bodies, 3), dtype=values.dtype)
    return zeros.at[np.asarray(index, dtype=np.int32)].add(values)


def rotor_forces(scene, params, phys, nodes, inputs: ActuatorInputs) -> Loads:
    """Force stage: rotor thrust (world, at the CoM) and rotor torques (body frame)."""
    qs = scene.quadrotor
    body = np.asarray(qs.body, dtype=np.int32)
    thrust, torque = rotor_wrench(params.quadrotor, inputs.rotor_speed_sq)
    zero = jnp.zeros_like(thrust)
    force = quat_rotate(phys.body_quat[body], jnp.stack([zero, zero, thrust], axis=-1))
    dtype = force.dtype
    return Loads(node_force=jnp.zeros((scene.n_nodes, 3), dtype=dtype),
                 body_force=_on_bodies(scene, force, body), body_torque=_on_bodies(scene, torque, body))
