"""Setpoints: what the cascaded PID tracks in one control period.

A :class:`Setpoint` gives every quadrotor a position, a velocity and a yaw (and, when
the source has them, feed-forward terms). A caller — a script, a policy, a test —
passes one as the ``control`` argument of :func:`mysim_jax.sim.step`::

    sp = Setpoint.hold(jnp.array([[0.0, 0.0, 1.5]]), yaw=0.3)     # one quadrotor
    state = step(scene, params, state, sp)

The controller runs once per environment step, at its start, and its motor command is
held over the step's physics sub-steps (zero-order hold): a setpoint is held for one
control period. What ``control`` is selects the source when the step is traced (the
Python type, static; no traced switch), in :mod:`mysim_jax.control.actuation`:

* a :class:`Setpoint` — the controller tracks it;
* an array ``(n_quads, 4)`` — raw motor speeds (rad/s), the controller is bypassed;
* ``None`` — the scene's reference trajectory (:func:`reference_setpoint`); a scene
  whose quadrotors have a controller but no ``reference`` raises, asking for setpoints.

**Modes** (``controller.setpoint_mode``, static: ``QuadrotorScene.setpoint_mode``; the
control laws are in :mod:`mysim_jax.control.pid`): ``position`` tracks ``position``
with ``velocity`` as velocity feed-forward (zero from :meth:`Setpoint.hold`);
``velocity`` ignores ``position`` and tracks ``velocity``. ``yaw`` is tracked in both.

**Limits** (``controller.flyable_box`` and ``controller.max_speed``, traced as
``ControlParams.box_low/box_high/max_speed`` so that vmapped sweeps can vary them).
Inside the step, :func:`limit_setpoint` maps every setpoint, whatever its source, into
them before the controller sees it:

* ``position`` is clipped to the box per axis;
* ``velocity`` is scaled down to ``max_speed`` if faster (its direction kept);
* with ``controller.descent_limit: braking`` (velocity mode), a descent is slowed to what
  the vehicle can stop from above the box's floor (:func:`brake_descent`);
* velocity components pointing out of the box are zeroed where the point they apply to
  is at or beyond that face: in position mode the setpoint's own (unclipped) position,
  in velocity mode the vehicle's position. A velocity setpoint therefore stops
  commanding motion through a face once the vehicle reaches it (the vehicle's lag can
  carry it slightly past; the box limits commands, it is not a wall).

A reference inside the limits passes through unchanged, bit for bit (the config check
:func:`~mysim_jax.config.quadrotor.reference_problems` makes sure of it for references
from a file). :func:`setpoint_from_action` maps a policy's normalised action in
``[-1, 1]`` onto the box (position mode) or onto ``±max_speed`` (velocity mode). For
setpoints written in a config or a script, :func:`mysim_jax.config.quadrotor.check_setpoint`
rejects values beyond the limits before anything runs, naming the field.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.control.pid import flat_body_rates
from mysim_jax.control.reference import reference
from mysim_jax.dynamics.quadrotor import top_thrust


@struct.dataclass
class Setpoint:
    """The setpoint of every quadrotor for one control period (world frame).

    The feed-forward fields are optional (``None`` feeds zeros); they are what the
    reference supplies (:func:`reference_setpoint`) and are used as the controller's
    ``feedforward`` option says (``acceleration``: ``acceleration``; ``full``: all
    three).
    """

    position: jnp.ndarray                          # (n_quads, 3) m (ignored in velocity mode)
    velocity: jnp.ndarray                          # (n_quads, 3) m/s (feed-forward in position mode)
    yaw: jnp.ndarray                               # (n_quads,) rad
    acceleration: jnp.ndarray | None = None        # (n_quads, 3) m/s^2, feed-forward
    body_rate: jnp.ndarray | None = None           # (n_quads, 3) rad/s, desired body frame, feed-forward
    body_angular_acceleration: jnp.ndarray | None = None   # (n_quads, 3) rad/s^2, desired body frame

    @classmethod
    def hold(cls, position, yaw=0.0) -> Setpoint:
        """Hover at ``position`` ``(n_quads, 3)`` m with heading ``yaw`` (rad, scalar or
        ``(n_quads,)``), zero velocity feed-forward."""
        position = jnp.asarray(position)
        return cls(position=position, velocity=jnp.zeros_like(position), yaw=_yaw_like(yaw, position))

    @classmethod
    def track(cls, position, velocity, yaw=0.0, acceleration=None) -> Setpoint:
        """Position ``(n_quads, 3)`` m with velocity ``(n_quads, 3)`` m/s (and optional
        acceleration ``(n_quads, 3)`` m/s²) as feed-forward: a point moving along a path."""
        position = jnp.asarray(position)
        return cls(position=position, velocity=jnp.asarray(velocity, dtype=position.dtype),
                   yaw=_yaw_like(yaw, position),
                   acceleration=None if acceleration is None else jnp.asarray(acceleration, dtype=position.dtype))

    @classmethod
    def from_velocity(cls, velocity, yaw=0.0) -> Setpoint:
        """Fly at ``velocity`` ``(n_quads, 3)`` m/s with heading ``yaw`` (velocity mode;
        ``position`` is zero and unused there)."""
        velocity = jnp.asarray(velocity)
        return cls(position=jnp.zeros_like(velocity), velocity=velocity, yaw=_yaw_like(yaw, velocity))


def _yaw_like(yaw, vectors):
    return jnp.broadcast_to(jnp.asarray(yaw, dtype=vectors.dtype), vectors.shape[:-1])


def reference_setpoint(params, t) -> Setpoint:
    """The scene's reference at time ``t`` (s, scalar) as a setpoint: position, velocity,
    yaw, and as feed-forward the acceleration and the flat body rate and angular
    acceleration (:func:`~mysim_jax.control.pid.flat_body_rates`)."""
    cp = params.controller
    if cp is None or cp.reference is None:
        raise ValueError("the scene has no reference trajectory (quadrotors.i.reference): pass setpoints")
    ref = reference(cp.reference, t)
    omega, alpha = flat_body_rates(params, t)
    return Setpoint(position=ref.pos, velocity=ref.vel, yaw=ref.yaw, acceleration=ref.acc,
                    body_rate=omega, body_angular_acceleration=alpha)


def as_setpoint(setpoint: Setpoint, n_quads: int, dtype) -> Setpoint:
    """``setpoint`` in ``dtype`` with its shapes checked (trace time; a scalar yaw is
    broadcast). Raises ValueError naming the field."""
    expected = {"position": (n_quads, 3), "velocity": (n_quads, 3), "yaw": (n_quads,), "acceleration": (n_quads, 3),
                "body_rate": (n_quads, 3), "body_angular_acceleration": (n_quads, 3)}
    fields = {}
    for name, shape in expected.items():
        value = getattr(setpoint, name)
        if value is None:
            if name in ("position", "velocity", "yaw"):
                raise ValueError(f"Setpoint.{name} is None: give an array {shape} (Setpoint.hold, "
                                 "Setpoint.track, Setpoint.from_velocity fill in what is not given)")
            fields[name] = None
            continue
        value = jnp.asarray(value, dtype=dtype)
        if name == "yaw" and value.ndim == 0:
            value = jnp.broadcast_to(value, shape)
        if value.shape != shape:
            raise ValueError(f"Setpoint.{name}: shape {tuple(value.shape)}, the scene has {n_quads} "
                             f"quadrotor(s): expected {shape} (one environment; vmap for a batch)")
        fields[name] = value
    return Setpoint(**fields)


def limit_setpoint(setpoint: Setpoint, controller_params, mode: str, vehicle_position) -> Setpoint:
    """``setpoint`` mapped into the flyable box and the speed limit (module docstring).
    ``vehicle_position`` ``(n_quads, 3)`` m: where the quadrotors are (velocity mode)."""
    low, high = controller_params.box_low, controller_params.box_high
    max_speed = controller_params.max_speed
    velocity = setpoint.velocity
    speed = vecmath.safe_norm(velocity)
    too_fast = speed > max_speed
    velocity = jnp.where(too_fast[:, None], velocity * (max_speed / jnp.where(too_fast, speed, 1.0))[:, None],
                         velocity)
    if mode == "position":
        beyond_high, beyond_low = setpoint.position > high, setpoint.position < low
    else:
        beyond_high, beyond_low = vehicle_position >= high, vehicle_position <= low
    outward = (beyond_high & (velocity > 0.0)) | (beyond_low & (velocity < 0.0))
    velocity = jnp.where(outward, 0.0, velocity)
    return setpoint.replace(position=jnp.clip(setpoint.position, low, high), velocity=velocity)


BRAKING_SHARE = 0.5     # of the upward acceleration beyond the weight that brake_descent plans to use


def brake_descent(setpoint: Setpoint, scene, params, vehicle_position) -> Setpoint:
    """Velocity mode, quadrotors with ``controller.descent_limit: braking``: the descent
    setpoint slowed to ``v_z >= -sqrt(2 b (z - z_low))``, where ``z_low`` is the flyable
    box's floor and ``b`` the braking deceleration planned, ``BRAKING_SHARE`` times
    ``T_max / m - g`` (``T_max = Σ c_L ω_max²``, the rotors' top thrust at their present top
    speed, which a motor fault lowers; ``m`` the mass the controller assumes). A vehicle at
    or below the floor gets no descent; one short of thrust to hover is planned a small
    deceleration (1 mm/s²) rather than none. Others pass unchanged."""
    qs, qp, cp = scene.quadrotor, params.quadrotor, params.controller
    braking = jnp.asarray([d == "braking" for d in qs.descent_limit], dtype=bool)
    t_max = top_thrust(qp)
    spare = t_max / cp.mass - vecmath.safe_norm(params.gravity)
    b = BRAKING_SHARE * jnp.maximum(spare, 1e-3)
    room = jnp.maximum(vehicle_position[:, 2] - cp.box_low[:, 2], 0.0)
    slowest = -jnp.sqrt(2.0 * b * room)
    v_z = jnp.where(braking, jnp.maximum(setpoint.velocity[:, 2], slowest), setpoint.velocity[:, 2])
    return setpoint.replace(velocity=setpoint.velocity.at[:, 2].set(v_z))


def setpoint_from_action(scene, params, action, yaw=0.0) -> Setpoint:
    """A policy's normalised action ``(n_quads, 3)`` in ``[-1, 1]`` as a setpoint:
    position mode maps it affinely onto the flyable box (−1 → ``low``, +1 → ``high``),
    velocity mode onto ``action · max_speed`` (then limited to ``max_speed`` in norm
    by :func:`limit_setpoint`). ``yaw`` in rad."""
    cp = params.controller
    action = jnp.asarray(action, dtype=cp.box_low.dtype)
    if scene.quadrotor.setpoint_mode == "velocity":
        return Setpoint.from_velocity(action * cp.max_speed[:, None], yaw)
    return Setpoint.hold(cp.box_low + 0.5 * (action + 1.0) * (cp.box_high - cp.box_low), yaw)
