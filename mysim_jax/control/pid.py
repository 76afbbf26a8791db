"""Cascaded PID for quadrotors (paper Fig. entire_controller_pd, Table PID_controller).

One call per environment step (the command is held over the step's sub-steps). The
controller tracks a :class:`~mysim_jax.control.setpoint.Setpoint` — position ``r_s``,
velocity ``v_s``, yaw ``ψ_s`` and optional feed-forward acceleration ``a_s``, body rate
``ω_s`` and body angular acceleration ``α_s`` — which the control stage
(:mod:`mysim_jax.control.actuation`) takes from the caller or from the scene's reference
(:func:`~mysim_jax.control.setpoint.reference_setpoint`) and limits to the flyable box
and ``max_speed`` first.

1. **Position loop** (world axes, gains in N/m, N/(m s), N s/m), by ``setpoint_mode``:

   * ``position`` (default): with ``e = r_s − r``, ``ė = v_s − v`` and ``I = ∫ e dt``,

         F_d = m (g↑ + a_s) + K_p e + K_i I + K_d ė

     (``v_s`` is a velocity feed-forward: zero for a plain position setpoint, the
     reference's velocity when the reference is the source);
   * ``velocity``: the position error is dropped and the loop tracks ``v_s``,

         F_d = m (g↑ + a_s) + K_d (v_s − v)

     with the position loop's ``K_d``. There is no integral term: the one gain of the
     position loop with the units for ``∫(v_s − v) dt`` (m) is ``K_p``, and
     ``K_p ∫(v_s − v) dt`` makes the loop the position loop again, tracking the path
     the setpoint integrates — lightly damped with the paper's gains (so velocity steps
     overshoot), and winding up whenever the speed limit or the box stops the vehicle
     short of that path. With P alone each axis follows its setpoint as a first-order
     lag of time constant ``m / K_d``, without overshoot; a constant force ``F`` (wind,
     a taut tether) leaves a velocity error ``F / K_d``, which the caller corrects with
     its next setpoints. The position integrator stays untouched.

   ``F_d`` is limited to ``max_tilt`` from vertical (and to at least a tenth of the
   weight upwards). With ``thrust_limit: vertical_priority`` it is then limited to the
   rotors' top thrust ``T_max = Σ c_L ω_max²`` (the motors' present top speed, which a
   motor fault lowers; the allocation's limits): the vertical part first,
   ``F_z ← min(F_z, T_max)``, and the horizontal part to what is left,
   ``|F_xy| ≤ √(T_max² − F_z²)`` (PX4's thrust-vector saturation). Without it
   (``none``, the default) a demand beyond ``T_max`` is handed on, and the allocation
   gives less thrust along the tilted axis, losing height with the horizontal push.
2. **Desired attitude** (Lee, Leok & McClamroch 2010): ``b₃ = F_d/|F_d|``,
   ``b₂ = b₃ × (cos ψ_s, sin ψ_s, 0)`` normalised, ``b₁ = b₂ × b₃``; thrust
   ``T = F_d · (R e_z)``.
3. **Attitude loop** (body axes): attitude error ``e_R = ½ (R_dᵀR − RᵀR_d)^∨`` (rad for
   small errors), rate error ``e_ω = ω − RᵀR_d ω_s``,
   ``u = −(K_p e_R + K_i ∫e_R dt + K_d e_ω)``, torque ``τ = s ⊙ u + τ_ff`` with
   ``τ_ff = ω × Jω − J(ω × RᵀR_d ω_s − RᵀR_d α_s)``.
4. **Allocation** about the centre of mass of the whole vehicle: cameras move it to
   ``r_c`` (body frame), so the rotors must add ``r_c × (0, 0, T)`` to hold the attitude;
   ``ω² = M⁻¹ (T, τ + r_c × T e_z)``, clipped to the motor limits (``saturation: clip``,
   the default). When a motor would leave its limits, each one is clipped alone, so the
   torque the rotors give is no longer ``τ``: with all four at their top speed a vehicle
   has no torque left and tips. ``saturation: attitude_priority`` instead keeps the
   torque and moves the collective thrust, as flight stacks' mixers do (PX4's
   desaturation): with ``a = M⁻¹ (1, r_c × e_z)`` (per motor, ``ω²`` per newton of
   thrust) and ``d = M⁻¹ (0, τ)``, every thrust ``T'`` in ``[L, U]`` with
   ``L = maxᵢ (ω²_min − dᵢ)/aᵢ``, ``U = minᵢ (ω²_max − dᵢ)/aᵢ`` keeps every motor inside
   its limits, and the allocation takes ``T' = clip(T, L, U)``, the feasible thrust closest to
   the demand. When no thrust fits the whole torque (``L > U``), the yaw torque is
   scaled down by the largest factor in ``[0, 1]`` that fits with the full roll and
   pitch torques; when those alone do not fit, yaw is dropped and roll and pitch are
   scaled down alike (:func:`attitude_priority_speeds`). A command inside the limits is
   the same under both.
5. **Anti-windup**: both integrators are clamped to their limits and frozen while any
   motor of that quadrotor saturates; the position integrator also while the tilt
   limit is active (position mode; velocity mode has none).

**Feed-forward** (``feedforward``; the paper: "utilizing its differential flatness
property"). ``full`` (default): ``m a_s`` in step 1, and ``ω_s``, ``α_s`` in step 3 —
for the reference, the body rate and acceleration of the attitude it alone asks for,
from its jerk and snap (:func:`flat_body_rates`). ``acceleration``: ``m a_s`` only
(``ω_s = α_s = 0``, ``τ_ff = 0``). ``none``: plain PID. A setpoint without feed-forward
terms (``None``) feeds zeros. The paper's gains are soft (position loop
ω_n ≈ 1.2 rad/s, ζ = 0.2–0.4; attitude ω_n ≈ 7 rad/s), so along a reference the
feed-forward carries the tracking and the PID corrects (docs/physics.md, "Quadrotor & control"
has the numbers for all three).

**Units of the paper's attitude gains** (``attitude_gain_units``; ``s`` above). Read as
SI torque gains, 7e4 N m/rad on ``J = 1.4e-4 kg m²`` is a 22 000 rad/s loop that no
motor can follow: the vehicle does not fly. Two readings make them fly:

* ``dyne_cm`` (default): CGS torque units, 1 dyn cm = 1e-7 N m (``s = 1e-7``). In CGS the
  inertia is J = 1400 g cm² (roll, pitch) and 2170 g cm² (yaw), and the paper's gains
  are a textbook design: roll/pitch ``ω_n = √(kp/J) = 7.1 rad/s`` with
  ``ζ = kd / (2√(kp J)) = 1.01`` (critically damped), yaw ``ω_n = 5.3 rad/s, ζ = 0.53``.
* ``rotor_speed_squared``: the attitude PID outputs a differential squared motor speed
  (rad²/s² per rad) that the mixer adds with ± signs to all four rotors, so
  ``s_a = Σ_i |M[a, i]|`` = ``4 (√2/2) l c = 7.82e-8 N m s²`` (roll/pitch),
  ``4 k = 2.90e-8 N m s²`` (yaw): roll/pitch ``ω_n = 6.3 rad/s, ζ = 0.89``, yaw
  ``ω_n = 2.8 rad/s, ζ = 0.28`` (yaw rings: 40 % overshoot on a 0.5 rad yaw step
  against 14 % for ``dyne_cm``).

``torque`` takes the gains as SI (``s = 1``), for gains tuned in SI.

Controller memory (:class:`ControlState`) lives in the environment State, so the whole
closed loop is a pure function of (Params, State) and vmaps; the gains are Params, so
it differentiates (:mod:`mysim_jax.tuning.gains`).
"""

from __future__ import annotations

import abc
from typing import final

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.control.reference import ReferenceParams, reference_derivatives
from mysim_jax.dynamics.quadrotor import allocation_inverse, allocation_matrix, top_thrust
from mysim_jax.dynamics.quaternion import quat_to_matrix

# torque per unit of attitude-PID output for the unit readings that are plain constants
ATTITUDE_UNIT_SCALE = {"torque": 1.0, "dyne_cm": 1e-7}


@struct.dataclass
class PIDGains:
    """Per-quadrotor, per-axis gains (the units of ControllerConfig)."""

    position_kp: jnp.ndarray   # (n_quads, 3) N/m
    position_ki: jnp.ndarray   # (n_quads, 3) N/(m s)
    position_kd: jnp.ndarray   # (n_quads, 3) N s/m
    attitude_kp: jnp.ndarray   # (n_quads, 3) per rad, in attitude_gain_units (dyn cm, rad^2/s^2 or N m)
    attitude_ki: jnp.ndarray   # (n_quads, 3) per rad s
    attitude_kd: jnp.ndarray   # (n_quads, 3) per rad/s


@struct.dataclass
class ControlParams:
    """Traced controller parameters: gains, the controller's model, setpoint limits,
    references (None in a scene driven by setpoints only)."""

    gains: PIDGains
    mass: jnp.ndarray                     # (n_quads,) kg, what the controller assumes
    com_offset: jnp.ndarray               # (n_quads, 3) m, vehicle CoM in the UAV body frame
    inertia: jnp.ndarray                  # (n_quads, 3, 3) kg m^2, vehicle inertia (feed-forward)
    max_tilt: jnp.ndarray                 # (n_quads,) rad
    position_integral_limit: jnp.ndarray  # (n_quads,) m s
    attitude_integral_limit: jnp.ndarray  # (n_quads,) rad s
    box_low: jnp.ndarray                  # (n_quads, 3) m, world: flyable box, lower corner
    box_high: jnp.ndarray                 # (n_quads, 3) m, world: flyable box, upper corner
    max_speed: jnp.ndarray                # (n_quads,) m/s, limit of velocity setpoints
    reference: ReferenceParams | None


@struct.dataclass
class ControlState:
    """Controller and motor memory of every quadrotor (part of the environment State)."""

    position_integral: jnp.ndarray  # (n_quads, 3) m s
    attitude_integral: jnp.ndarray  # (n_quads, 3) rad s
    motor_speed: jnp.ndarray        # (n_quads, 4) rad/s at the end of the last step
    motor_command: jnp.ndarray      # (n_quads, 4) rad/s commanded for the last step (clipped)
    steps: jnp.ndarray              # () int32, environment steps taken: the controller's clock


def control_time(scene, memory):
    """The controller's clock ``steps · dt`` (s). Exact to float rounding of one product,
    unlike ``State.time``, which sums ``dt`` every step and in float32 drifts by ~1e-4
    relative (1.2 ms after 12 s of 1 ms steps) — enough to show as mm of tracking error."""
    dtype = memory.position_integral.dtype
    return memory.steps.astype(dtype) * jnp.asarray(scene.dt, dtype=dtype)


class Controller(abc.ABC):
    """A quadrotor controller, evaluated once per environment step.

    ``command(scene, params, state, setpoint)`` returns ``(omega_cmd (n_quads, 4) rad/s,
    memory)``: the motor speeds to hold over the step towards ``setpoint`` (a
    :class:`~mysim_jax.control.setpoint.Setpoint`, already limited, in the state's
    dtype) and the updated :class:`ControlState` (``motor_speed``/``motor_command`` are
    filled in afterwards by the motor model). Must be pure and written for one
    environment.
    """

    @abc.abstractmethod
    def command(self, scene, params, state, setpoint):
        ...


def safe_sqrt(x, tiny: float = 1e-12):
    """``sqrt(max(x, 0))`` with a finite gradient at 0."""
    positive = x > tiny
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def attitude_torque_gain(scene, qp):
    """Torque per unit attitude-PID output ``(n_quads, 3)`` (see module docstring)."""
    per_sq = jnp.sum(jnp.abs(allocation_matrix(qp)[:, 1:, :]), axis=-1)
    units = scene.quadrotor.attitude_gain_units
    squared = np.asarray([u == "rotor_speed_squared" for u in units])[:, None]
    scale = np.asarray([ATTITUDE_UNIT_SCALE.get(u, 1.0) for u in units])[:, None]
    return jnp.where(squared, per_sq, jnp.asarray(scale, dtype=per_sq.dtype))


def desired_thrust(scene, params, state, setpoint):
    """Position loop: ``(F_d (n_quads, 3), tilt_limited (n_quads,), e (n_quads, 3))``, ``e``
    the position error (zeros in velocity mode)."""
    qs, cp = scene.quadrotor, params.controller
    body = np.asarray(qs.body, dtype=np.int32)
    phys = state.phys
    g = cp.gains
    e_dot = setpoint.velocity - phys.body_vel[body]
    up = -params.gravity
    acc = up[None, :]
    ff = np.asarray([f in ("acceleration", "full") for f in qs.feedforward])
    if ff.any() and setpoint.acceleration is not None:
        acc = acc + jnp.where(ff[:, None], setpoint.acceleration, 0.0)
    if qs.setpoint_mode == "position":
        e = setpoint.position - phys.body_pos[body]
        force = cp.mass[:, None] * acc + g.position_kp * e + g.position_ki * state.controller.position_integral \
            + g.position_kd * e_dot
    elif qs.setpoint_mode == "velocity":
        e = jnp.zeros_like(e_dot)
        force = cp.mass[:, None] * acc + g.position_kd * e_dot
    else:
        raise ValueError(f"unknown setpoint_mode '{qs.setpoint_mode}' (position | velocity)")
    # tilt limit: at least a tenth of the weight upwards, horizontal part within max_tilt
    f_z = jnp.maximum(force[:, 2], 0.1 * cp.mass * vecmath.safe_norm(up))
    horizontal = force.at[:, 2].set(0.0)
    h_norm = vecmath.safe_norm(horizontal)
    h_max = f_z * jnp.tan(cp.max_tilt)
    tilt_limited = h_norm > h_max
    scale = jnp.minimum(1.0, h_max / jnp.maximum(h_norm, 1e-12))
    force = (horizontal * scale[:, None]).at[:, 2].set(f_z)
    vertical_first = np.asarray([t == "vertical_priority" for t in qs.thrust_limit], dtype=bool)
    if vertical_first.any():
        with jax.named_scope("thrust_vector_limit"):
            qp = params.quadrotor
            t_max = top_thrust(qp)      # (n_quads,) N
            f_z_kept = jnp.minimum(f_z, t_max)
            h_left = safe_sqrt(jnp.maximum(t_max ** 2 - f_z_kept ** 2, 0.0))
            h_now = h_norm * scale
            over = vecmath.safe_norm(force) > t_max
            shrink = jnp.minimum(1.0, h_left / jnp.maximum(h_now, 1e-12))
            limited = (horizontal * (scale * shrink)[:, None]).at[:, 2].set(f_z_kept)
            apply = vertical_first & over
            force = jnp.where(apply[:, None], limited, force)
            tilt_limited = tilt_limited | apply
    return force, tilt_limited, e


def attitude_error(rot_d, rot):
    """``½ (R_dᵀR − RᵀR_d)^∨`` ``(…, 3)`` (body frame)."""
    m = jnp.einsum("...ki,...kj->...ij", rot_d, rot)
    skew = 0.5 * (m - jnp.swapaxes(m, -1, -2))
    return jnp.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)


def desired_rotation(force, yaw):
    """Desired body axes ``(n_quads, 3, 3)`` (columns) from thrust direction and yaw."""
    _, b3 = vecmath.safe_unit(force)
    heading = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw)], axis=-1)
    _, b2 = vecmath.safe_unit(vecmath.cross(b3, heading))
    b1 = vecmath.cross(b2, b3)
    return jnp.stack([b1, b2, b3], axis=-1)


def _vee(m):
    """Axial vector ``(…, 3)`` of the antisymmetric part of ``m`` ``(…, 3, 3)``."""
    skew = 0.5 * (m - jnp.swapaxes(m, -1, -2))
    return jnp.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)


def flat_body_rates(params, t):
    """Angular velocity and acceleration ``(n_quads, 3)`` each (desired body frame) of the
    attitude the reference alone asks for, ``R_ref(t)`` from ``F = g↑ + a_d(t)`` and
    ``ψ_d(t)``: ``ω_d = (R_refᵀ Ṙ_ref)^∨``, ``α_d = (R_refᵀ R̈_ref)^∨`` (the symmetric
    part ``ω̂²`` drops out). ``Ṙ``, ``R̈`` come from second-order forward-mode autodiff of
    :func:`desired_rotation` along ``F(t), ψ(t)``, fed with the reference's jerk and snap."""
    cp = params.controller
    pos, yaw = reference_derivatives(cp.reference, t)
    force = (-params.gravity)[None, :] + pos[2]

    def along(u):
        return desired_rotation(force + u * pos[3] + 0.5 * u * u * pos[4],
                                yaw[0] + u * yaw[1] + 0.5 * u * u * yaw[2])

    def first(u):
        return jax.jvp(along, (u,), (jnp.ones_like(u),))

    u0 = jnp.zeros((), dtype=force.dtype)
    (rot, rot_dot), (_, rot_ddot) = jax.jvp(first, (u0,), (jnp.ones_like(u0),))
    omega = _vee(jnp.einsum("...ki,...kj->...ij", rot, rot_dot))
    alpha = _vee(jnp.einsum("...ki,...kj->...ij", rot, rot_ddot))
    return omega, alpha


def _feasible_interval(a, d, lo, hi):
    """The thrusts ``[L, U]`` (per quadrotor) that keep every motor of ``a T + d`` within
    ``[lo, hi]`` (``a > 0``); empty when ``L > U``."""
    return jnp.max((lo - d) / a, axis=-1), jnp.min((hi - d) / a, axis=-1)


def _largest_fitting_fraction(a, base, extra, lo, hi):
    """The largest ``γ`` in ``[0, 1]`` for which some thrust ``T`` keeps every motor of
    ``a T + base + γ extra`` within ``[lo, hi]``, given that ``γ = 0`` fits. A thrust fits
    ``γ`` when ``(lo − baseᵢ − γ extraᵢ)/aᵢ <= (hi − baseⱼ − γ extraⱼ)/aⱼ`` for every pair
    of motors ``i, j``; each pair whose bound tightens with ``γ`` caps it."""
    low = (lo - base) / a                                   # (n_quads, 4): motor i's lower bound on T at γ = 0
    high = (hi - base) / a
    slope = extra / a
    room = high[..., None, :] - low[..., :, None]           # [i, j]: U_j − L_i at γ = 0 (>= 0 when it fits)
    tightening = slope[..., None, :] - slope[..., :, None]  # [i, j]: how fast U_j − L_i shrinks with γ
    safe = jnp.where(tightening > 0, tightening, 1.0)
    cap = jnp.where(tightening > 0, room / safe, jnp.inf)
    return jnp.clip(jnp.min(cap, axis=(-2, -1)), 0.0, 1.0)


def attitude_priority_speeds(inverse, thrust, torque, com_offset, lo, hi):
    """Squared motor speeds ``(n_quads, 4)`` that keep the roll and pitch torque, then the
    yaw torque, and move the collective thrust to the nearest that fits the motor limits
    ``[lo, hi]`` (``saturation: attitude_priority``, module docstring step 4).

    ``inverse`` is ``M⁻¹`` (n_quads, 4, 4), ``thrust`` (n_quads,) N, ``torque``
    (n_quads, 3) N m the attitude loop's torque about the vehicle's centre of mass,
    ``com_offset`` (n_quads, 3) m its offset from the rotors' centre (the allocation adds
    ``com_offset × T e_z``, a torque that moves with the thrust). The result may still
    leave the limits by round-off; the caller clips it.
    """
    e_z = jnp.zeros_like(com_offset).at[:, 2].set(1.0)
    per_thrust = jnp.concatenate([jnp.ones_like(thrust)[:, None], vecmath.cross(com_offset, e_z)], axis=-1)
    a = jnp.einsum("qij,qj->qi", inverse, per_thrust)                      # ω² per N of thrust, > 0
    roll_pitch = jnp.einsum("qij,qj->qi", inverse[:, :, 1:3], torque[:, :2])
    yaw = inverse[:, :, 3] * torque[:, 2:3]
    low, high = _feasible_interval(a, roll_pitch, lo, hi)
    roll_pitch_fits = low <= high
    yaw_kept = jnp.where(roll_pitch_fits, _largest_fitting_fraction(a, roll_pitch, yaw, lo, hi), 0.0)
    roll_pitch_kept = jnp.where(roll_pitch_fits, 1.0,
                                _largest_fitting_fraction(a, jnp.zeros_like(roll_pitch), roll_pitch, lo, hi))
    d = roll_pitch_kept[:, None] * roll_pitch + yaw_kept[:, None] * yaw
    low, high = _feasible_interval(a, d, lo, hi)
    kept_thrust = jnp.minimum(jnp.maximum(thrust, low), high)
    return a * kept_thrust[:, None] + d


@final
class CascadedPID(Controller):
    """Position PID → desired attitude → attitude PID → allocation (module docstring)."""

    def command(self, scene, params, state, setpoint):
        qs, qp, cp = scene.quadrotor, params.quadrotor, params.controller
        body = np.asarray(qs.body, dtype=np.int32)
        phys, memory = state.phys, state.controller
        g = cp.gains
        dt = jnp.asarray(scene.dt, dtype=phys.body_pos.dtype)

        force, tilt_limited, e_pos = desired_thrust(scene, params, state, setpoint)
        rot = quat_to_matrix(phys.body_quat[body])
        rot_d = desired_rotation(force, setpoint.yaw)
        thrust = vecmath.dot(force, rot[..., 2])
        e_att = attitude_error(rot_d, rot)
        omega = phys.body_angvel[body]
        full = np.asarray([f == "full" for f in qs.feedforward])[:, None]
        omega_ref = alpha_ref = jnp.zeros_like(omega)
        if full.any():
            # flatness feed-forward (Lee et al. 2010): track the setpoint's body rates
            to_body = jnp.einsum("...ki,...kj->...ij", rot, rot_d)        # Rᵀ R_d
            if setpoint.body_rate is not None:
                omega_ref = jnp.where(full, jnp.einsum("qij,qj->qi", to_body, setpoint.body_rate), 0.0)
            if setpoint.body_angular_acceleration is not None:
                alpha_ref = jnp.where(full, jnp.einsum("qij,qj->qi", to_body, setpoint.body_angular_acceleration),
                                      0.0)
        u = -(g.attitude_kp * e_att + g.attitude_ki * memory.attitude_integral
              + g.attitude_kd * (omega - omega_ref))
        torque = attitude_torque_gain(scene, qp) * u
        if full.any():
            inertia = cp.inertia
            j_omega = jnp.einsum("qij,qj->qi", inertia, omega)
            j_terms = jnp.einsum("qij,qj->qi", inertia, vecmath.cross(omega, omega_ref) - alpha_ref)
            torque = torque + jnp.where(full, vecmath.cross(omega, j_omega) - j_terms, 0.0)
        # allocate about the vehicle's centre of mass (cameras move it off the body centre)
        zero = jnp.zeros_like(thrust)
        inverse = allocation_inverse(qp)
        wrench = jnp.concatenate(
            [thrust[:, None], torque + vecmath.cross(cp.com_offset, jnp.stack([zero, zero, thrust], axis=-1))],
            axis=-1)
        speed_sq = jnp.einsum("qij,qj->qi", inverse, wrench)
        lo, hi = qp.omega_min[:, None] ** 2, qp.omega_max[:, None] ** 2
        saturated = jnp.any((speed_sq < lo) | (speed_sq > hi), axis=-1)
        priority = np.asarray([s == "attitude_priority" for s in qs.saturation], dtype=bool)
        if priority.any():
            with jax.named_scope("attitude_priority_allocation"):
                kept = attitude_priority_speeds(inverse, thrust, torque, cp.com_offset, lo, hi)
            speed_sq = jnp.where((priority & saturated)[:, None], kept, speed_sq)
        clipped = jnp.clip(speed_sq, lo, hi)
        omega_cmd = safe_sqrt(clipped)

        pos_lim = cp.position_integral_limit[:, None]
        att_lim = cp.attitude_integral_limit[:, None]
        new_att = jnp.clip(memory.attitude_integral + e_att * dt, -att_lim, att_lim)
        position_integral = memory.position_integral       # velocity mode: no position integrator
        if qs.setpoint_mode == "position":
            new_pos = jnp.clip(memory.position_integral + e_pos * dt, -pos_lim, pos_lim)
            hold_pos = (saturated | tilt_limited)[:, None]
            position_integral = jnp.where(hold_pos, memory.position_integral, new_pos)
        hold_att = saturated[:, None]
        memory = memory.replace(
            position_integral=position_integral,
            attitude_integral=jnp.where(hold_att, memory.attitude_integral, new_att),
        )
        return omega_cmd, memory


CONTROLLERS: dict[str, Controller] = {"cascaded_pid": CascadedPID()}
