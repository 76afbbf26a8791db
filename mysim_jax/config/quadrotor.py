"""Configuration of quadrotors: rotors, motors, aerodynamics, controller, reference
trajectory and cameras (the ``quadrotors:`` section of a scene file).

Every default is the paper's (Table UAV_model, Table PID_controller, Table camera) unless
its docstring says otherwise. This module only depends on pydantic so that
:mod:`mysim_jax.config.scene` can import it; :func:`quadrotor_problems` is the whole-scene
check that :class:`~mysim_jax.config.scene.SceneConfig` calls (bodies that do not exist,
name clashes, a reference outside the flyable box, ...); :func:`check_setpoint` checks
setpoints written in a file or script against the same limits.

A minimal quadrotor names its rigid body (mass and inertia live on the body) and a
reference::

    bodies:
      - {name: uav0, mass: 0.28, inertia: [1.4e-4, 1.4e-4, 2.17e-4], pos: [0, 0, 1]}
    quadrotors:
      - body: uav0
        reference: {center: [0, 0, 1]}          # hover
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator
from pydantic import ValidationError

from mysim_jax.core.config_base import (ConfigError, Finite, Name, NonNegFloat, NonNegVec3, Pair, PosFloat, PosPair,
                                        PosVec4, StrictModel, UnitQuat, Vec3, Vec4, format_validation_error,
                                        read_yaml_file)
from mysim_jax.core.npgeom import rotate
from mysim_jax.dynamics.rotor_layout import allocation_matrix_np


# --- paper defaults ------------------------------------------------------------------
# Table UAV_model lists the rotor angles as 0.785, 2.36, 3.93, 5.50 rad: pi/4 + k pi/2
# rounded to three digits. The rounded values are not symmetric (the rotors' centre of
# thrust sits 0.4 mm off the body centre, so hover would need unequal motor speeds); the
# defaults are the exact angles the table rounds.
PAPER_ARM_LENGTH = (0.096, 0.096, 0.096, 0.096)                  # m
PAPER_ROTOR_ANGLE = tuple(math.pi / 4 + k * math.pi / 2 for k in range(4))   # rad
PAPER_LIFT_COEFFICIENT = (2.88e-7,) * 4                         # N s^2 / rad^2
PAPER_TORQUE_COEFFICIENT = (7.24e-9,) * 4                       # N m s^2 / rad^2
PAPER_SPIN = (1, -1, 1, -1)       # tau_psi = k (w1^2 - w2^2 + w3^2 - w4^2)
# Motor limit (the paper gives none): 2440 rad/s (23 300 rpm) gives the paper's 0.28 kg
# vehicle a thrust-to-weight ratio of 4 c w_max^2 / (m g) = 2.50, typical of small
# camera quadrotors (hover at 1544 rad/s = 63 % of the maximum speed).
DEFAULT_OMEGA_MAX = 2440.0                                      # rad/s
PAPER_POSITION_GAINS = {"kp": (0.4, 0.4, 1.25), "ki": (0.05, 0.025, 0.05), "kd": (0.2, 0.12, 0.5)}
PAPER_ATTITUDE_GAINS = {"kp": (7.0e4, 7.0e4, 6.0e4), "ki": (0.0, 0.0, 5.0e2), "kd": (2.0e4, 2.0e4, 1.2e4)}
PAPER_CAMERA_OFFSET = (0.03, 0.0, -0.03)                        # m, UAV body frame
PAPER_CAMERA_INERTIA = (2.17e-6, 4.83e-6, 5.67e-6)              # kg m^2
PAPER_CAMERA_MASS = 0.02                                        # kg
# Setpoint limits (the paper gives none). The box is a 20 m x 20 m x 10 m flight volume
# around the world origin; its floor sits 0.1 m above the ground plane z = 0 (the
# paper's vehicle is 0.27 m across), so no setpoint asks the vehicle into the ground.
# 10 m/s leaves room above the shipped references (uav_track_large is the fastest).
DEFAULT_BOX_LOW = (-10.0, -10.0, 0.1)                           # m, world
DEFAULT_BOX_HIGH = (10.0, 10.0, 10.0)                           # m, world
DEFAULT_MAX_SPEED = 10.0                                        # m/s


class RotorConfig(StrictModel):
    """Four rotors at ``d_i = l_i [sin θ_i, cos θ_i, 0]`` (body frame), thrust ``c_i ω_i²``
    along body z, reaction torque ``spin_i k_i ω_i²`` about body z (``spin = +1``: the
    rotor turns clockwise seen from above, so its drag torque on the body points up).

    Motor speeds are clipped to ``[omega_min, omega_max]`` (rad/s). ``time_constant``
    (s) adds first-order motor lag ``ω̇ = (ω_cmd − ω)/τ``; without it the motors follow
    their command instantly.
    """

    arm_length: PosVec4 = PAPER_ARM_LENGTH
    angle: Vec4 = PAPER_ROTOR_ANGLE
    lift_coefficient: PosVec4 = PAPER_LIFT_COEFFICIENT
    torque_coefficient: PosVec4 = PAPER_TORQUE_COEFFICIENT
    spin: tuple[Literal[1, -1], Literal[1, -1], Literal[1, -1], Literal[1, -1]] = PAPER_SPIN
    omega_min: NonNegFloat = 0.0
    omega_max: PosFloat = DEFAULT_OMEGA_MAX
    time_constant: PosFloat | None = None

    @model_validator(mode="after")
    def _check(self):
        if self.omega_min >= self.omega_max:
            raise ValueError(f"omega_min ({self.omega_min:g}) must be below omega_max ({self.omega_max:g})")

        m = allocation_matrix_np(self.arm_length, self.angle, self.lift_coefficient,
                                 self.torque_coefficient, self.spin)
        if np.linalg.cond(m) > 1e12:
            raise ValueError("rotor layout cannot produce independent thrust and three torques "
                             "(singular allocation matrix): check angle and spin")
        return self


class GainSet(StrictModel):
    """Per-axis PID gains ``[x, y, z]`` (position loop: world axes; attitude loop: body
    roll, pitch, yaw axes). All gains are non-negative."""

    kp: NonNegVec3
    ki: NonNegVec3
    kd: NonNegVec3


class FlyableBox(StrictModel):
    """An axis-aligned box ``low ≤ r ≤ high`` (m, world) that position setpoints are
    clipped to (see :mod:`mysim_jax.control.setpoint`)."""

    low: Vec3 = DEFAULT_BOX_LOW
    high: Vec3 = DEFAULT_BOX_HIGH

    @model_validator(mode="after")
    def _check(self):
        bad = [f"{a}: low {lo:g} >= high {hi:g}" for a, lo, hi in zip("xyz", self.low, self.high) if lo >= hi]
        if bad:
            raise ValueError(f"low must be below high on every axis ({'; '.join(bad)})")
        return self


class ControllerConfig(StrictModel):
    """The cascaded PID of paper Fig. entire_controller_pd (see :mod:`mysim_jax.control.pid`).

    ``position`` gains are in N/m, N/(m s), N s/m (Table PID_controller). ``attitude``
    gains are read in ``attitude_gain_units`` (see :mod:`mysim_jax.control.pid`):

    * ``dyne_cm`` (default): torque gains in CGS units, dyn cm/rad = 1e-7 N m/rad. The
      unit system in which the paper's gains are a textbook design (roll/pitch critically
      damped on J = 1400 g cm²); it flies the vehicle best of the readings tried;
    * ``rotor_speed_squared``: the attitude PID outputs a differential squared motor
      speed (rad²/s² per rad) that the mixer adds with ± signs to every rotor;
    * ``torque``: plain SI, N m/rad (with the paper's numbers the vehicle does not fly).

    ``feedforward`` (differential flatness): ``acceleration`` adds ``m a_d`` to the
    desired thrust; ``full`` (default) also feeds the reference's body rates and
    accelerations (from its jerk and snap) to the attitude loop; ``none`` is plain PID.
    ``saturation`` says what the allocation does when a motor would leave its limits:
    ``clip`` (default) clips each motor alone, which loses torque (all four at the top
    speed give none); ``attitude_priority`` keeps the torque and moves the collective
    thrust instead, giving up yaw, then roll and pitch, only when no thrust fits, as
    flight stacks' mixers do (:mod:`mysim_jax.control.pid`, step 4).
    ``thrust_limit`` says what the position loop does when its desired thrust is more than
    the rotors give at their top speed: ``none`` (default) asks for it anyway (the
    allocation then gives less, along the tilted axis, so the vertical part is lost with
    the horizontal); ``vertical_priority`` keeps the vertical part first and shortens the
    horizontal part to what is left, as flight stacks limit the thrust vector (step 1).
    ``descent_limit`` (velocity mode only): ``none`` (default) passes a descent setpoint as
    it is; ``braking`` slows it to what the vehicle can stop from above the flyable box's
    floor, ``v_z >= -sqrt(2 b (z - z_low))`` with ``b`` half the upward acceleration its
    rotors' present top thrust gives beyond its weight (a motor fault lowers it;
    :func:`mysim_jax.control.setpoint.brake_descent`).
    ``max_tilt`` (rad) limits the tilt of the desired thrust vector. Integrators are clamped to ``±position_integral_limit`` (m s) and
    ``±attitude_integral_limit`` (rad s) and frozen while a motor saturates
    (anti-windup). ``mass`` is the mass the controller assumes (default: the UAV body
    plus its cameras).

    Setpoints (:mod:`mysim_jax.control.setpoint`): ``setpoint_mode: position`` (default)
    tracks a position with an optional velocity feed-forward; ``velocity`` tracks a
    velocity (every quadrotor of a scene has the same mode). Inside the step, position
    setpoints are clipped to ``flyable_box`` (m, world; default x, y in ±10 m, z from
    0.1 m to 10 m) and velocity setpoints to the speed ``max_speed`` (m/s, default 10).
    """

    type: Literal["cascaded_pid"] = "cascaded_pid"
    position: GainSet = GainSet(**PAPER_POSITION_GAINS)
    attitude: GainSet = GainSet(**PAPER_ATTITUDE_GAINS)
    attitude_gain_units: Literal["dyne_cm", "rotor_speed_squared", "torque"] = "dyne_cm"
    feedforward: Literal["none", "acceleration", "full"] = "full"
    saturation: Literal["clip", "attitude_priority"] = "clip"
    thrust_limit: Literal["none", "vertical_priority"] = "none"
    descent_limit: Literal["none", "braking"] = "none"
    max_tilt: Annotated[Finite, Field(gt=0, lt=math.pi / 2)] = 0.8
    position_integral_limit: PosFloat = 2.0
    attitude_integral_limit: PosFloat = 1.0
    mass: PosFloat | None = None
    setpoint_mode: Literal["position", "velocity"] = "position"
    flyable_box: FlyableBox = FlyableBox()
    max_speed: PosFloat = DEFAULT_MAX_SPEED

    @model_validator(mode="after")
    def _descent_limit_needs_velocity_mode(self):
        if self.descent_limit != "none" and self.setpoint_mode != "velocity":
            raise ValueError(f"descent_limit: {self.descent_limit} limits velocity setpoints: it needs "
                             f"setpoint_mode: velocity (this controller's is {self.setpoint_mode}), or "
                             f"descent_limit: none")
        return self


class YawReference(StrictModel):
    """``ψ_d(t) = center + amplitude sin(multiple φ(t) + phase)`` (rad)."""

    center: Finite = 0.0
    amplitude: Finite = 0.0
    multiple: Finite = 1.0
    phase: Finite = 0.0


class ReferenceConfig(StrictModel):
    """A Lissajous reference ``r_d(t) = center + amplitude ⊙ sin(multiple ⊙ φ(t) + phase)``
    with ``φ(t) = 2π s(t) / period``. ``s(t)`` ramps the speed up smoothly over ``ramp``
    seconds (quintic smooth step on ``ṡ``, so position, velocity and acceleration of the
    reference are continuous and start from rest); after the ramp ``s(t) = t − ramp/2``.

    All amplitudes zero (the default) is a hover at ``center``. ``multiple = [1, 2, ·]``
    draws a figure-eight.
    """

    type: Literal["lissajous"] = "lissajous"
    center: Vec3
    amplitude: Vec3 = (0.0, 0.0, 0.0)
    multiple: Vec3 = (1.0, 2.0, 1.0)
    phase: Vec3 = (0.0, 0.0, 0.0)
    period: PosFloat = 1.0
    ramp: NonNegFloat = 0.0
    yaw: YawReference = YawReference()


class WindConfig(StrictModel):
    """Wind as a world-frame force on the UAV body (N): a constant part plus one
    ``1 − cos`` gust ``½ gust_force (1 − cos(2π (t − gust_start)/gust_duration))`` for
    ``gust_start <= t <= gust_start + gust_duration``."""

    force: Vec3 = (0.0, 0.0, 0.0)
    gust_force: Vec3 = (0.0, 0.0, 0.0)
    gust_start: NonNegFloat = 0.0
    gust_duration: PosFloat = 1.0


class ServoConfig(StrictModel):
    """PD angle servo of a gimbal: torque ``kp (a_cmd − a) − kd ȧ`` on each of the two
    axes (N m/rad, N m s/rad). The defaults give the Table camera a ~10 Hz, well
    damped servo (ω_n ≈ 60 rad/s, ζ ≈ 0.8)."""

    kp: PosPair = (0.02, 0.02)
    kd: PosPair = (5.0e-4, 5.0e-4)


class GimbalCommand(StrictModel):
    """Commanded gimbal angles ``angle + amplitude sin(2π t / period)`` (rad, per axis)."""

    angle: Pair = (0.0, 0.0)
    amplitude: Pair = (0.0, 0.0)
    period: PosPair = (1.0, 1.0)


class CameraConfig(StrictModel):
    """A camera body attached to the UAV (paper Fig. camera_fixed / camera_universal).

    ``mount: fixed`` — a fixed joint at ``offset`` (UAV body frame); the camera frame is
    the UAV frame rotated by ``quat`` (camera → UAV body).
    ``mount: gimbal`` — a universal joint at ``offset`` with a driven outer axis
    (``outer_axis``, UAV body frame) and inner axis (``inner_axis``, camera frame),
    perpendicular at zero angles, when the camera frame is the UAV frame rotated by
    ``quat``. The camera's centre of mass is the joint point.
    """

    name: Name
    mount: Literal["fixed", "gimbal"]
    offset: Vec3 = PAPER_CAMERA_OFFSET
    quat: UnitQuat = (1.0, 0.0, 0.0, 0.0)
    mass: PosFloat = PAPER_CAMERA_MASS
    inertia: tuple[PosFloat, PosFloat, PosFloat] = PAPER_CAMERA_INERTIA
    outer_axis: Vec3 = (0.0, 0.0, 1.0)
    inner_axis: Vec3 = (0.0, 1.0, 0.0)
    servo: ServoConfig = ServoConfig()
    command: GimbalCommand = GimbalCommand()

    @model_validator(mode="after")
    def _check(self):
        fields = type(self).model_fields
        gimbal_only = {k for k in ("outer_axis", "inner_axis", "servo", "command")
                       if getattr(self, k) != fields[k].default}
        if self.mount == "fixed" and gimbal_only:
            raise ValueError(f"{', '.join(sorted(gimbal_only))}: only a gimbal camera has these")
        a, b, c = sorted(self.inertia)
        if c > a + b + 1e-12 * c:
            raise ValueError(f"inertia {list(self.inertia)} violates the triangle inequality")
        if self.mount == "gimbal":
            outer, inner = np.asarray(self.outer_axis), np.asarray(self.inner_axis)
            if np.linalg.norm(outer) < 1e-9 or np.linalg.norm(inner) < 1e-9:
                raise ValueError("outer_axis and inner_axis must be non-zero")
            inner_in_body = rotate(self.quat, inner)
            cosine = abs(outer @ inner_in_body) / (np.linalg.norm(outer) * np.linalg.norm(inner))
            if cosine > 1e-6:
                raise ValueError(
                    f"outer_axis {list(self.outer_axis)} (UAV frame) and inner_axis {list(self.inner_axis)} "
                    f"(camera frame, rotated by quat) must be perpendicular (cos angle = {cosine:.3g})"
                )
        return self


class QuadrotorConfig(StrictModel):
    """A quadrotor: rotor forces on the rigid body ``body``, optionally under a
    controller, with optional drag, wind and cameras.

    The controller tracks ``reference`` when ``step`` is called without ``control``, or
    the :class:`~mysim_jax.control.setpoint.Setpoint` passed as ``control``; a scene
    driven by setpoints only (a script, a policy) leaves ``reference`` out. Either every
    controlled quadrotor of a scene has a reference or none has. ``drag`` (N s/m, body
    axes) is linear body drag ``F = −R D Rᵀ v``. ``controller: null`` leaves the motors
    to the ``control`` argument of ``step`` (commanded motor speeds, rad/s).
    """

    body: Name
    rotors: RotorConfig = RotorConfig()
    drag: NonNegVec3 | None = None
    wind: WindConfig | None = None
    controller: ControllerConfig | None = ControllerConfig()
    reference: ReferenceConfig | None = None
    cameras: list[CameraConfig] = []


def quadrotor_problems(scene) -> list[str]:
    """Whole-scene checks of ``scene.quadrotors`` (called by SceneConfig's validator)."""
    problems: list[str] = []
    bodies = {b.name: b for b in scene.bodies}
    taken = {p.name for p in scene.points} | set(bodies) | {a.name for a in scene.anchors}
    taken |= {r.name for r in scene.ropes} | {s.name for s in scene.springs}
    taken |= {f"{r.name}_{j}" for r in scene.ropes for j in range(r.n_masses)}
    seen_bodies: dict[str, int] = {}
    has_controller = [q.controller is not None for q in scene.quadrotors]
    has_reference = [q.reference is not None for q in scene.quadrotors if q.controller is not None]
    modes = [q.controller.setpoint_mode for q in scene.quadrotors if q.controller is not None] or ["position"]
    for i, q in enumerate(scene.quadrotors):
        where = f"quadrotors.{i}"
        if q.body not in bodies:
            known = ", ".join(sorted(bodies)) or "none"
            problems.append(f"{where}.body: '{q.body}' is not a body (bodies: {known})")
        elif q.body in seen_bodies:
            problems.append(f"{where}.body: body '{q.body}' is already quadrotors.{seen_bodies[q.body]}")
        else:
            seen_bodies[q.body] = i
        if q.controller is None and q.reference is not None:
            problems.append(f"{where}.reference: only used by a controller (controller is null)")
        if any(has_controller) and not all(has_controller):
            problems.append(f"{where}.controller: either every quadrotor has a controller or none has")
        if q.controller is not None:
            if any(has_reference) and not all(has_reference):
                problems.append(f"{where}.reference: either every quadrotor has a reference or none has "
                                "(a scene without references is driven by setpoints passed to step)")
            if q.controller.setpoint_mode != modes[0]:
                problems.append(f"{where}.controller.setpoint_mode: '{q.controller.setpoint_mode}', and "
                                f"quadrotors.0 has '{modes[0]}': every quadrotor of a scene has the same mode")
            if q.reference is not None:
                problems += reference_problems(q.reference, q.controller, where)
        marker_names = {m.name for m in bodies[q.body].markers} if q.body in bodies else set()
        for j, cam in enumerate(q.cameras):
            if cam.name in taken:
                problems.append(f"{where}.cameras.{j}.name: '{cam.name}' is already used")
            taken.add(cam.name)
            if f"{cam.name}_mount" in marker_names:
                problems.append(f"{where}.cameras.{j}.name: body '{q.body}' already has a marker "
                                f"'{cam.name}_mount' (the camera's mount marker)")
    return problems


def reference_speed_bound(ref: ReferenceConfig) -> float:
    """An upper bound (m/s) on the reference's speed: ``|ṙ_d| ≤ 2π/period · |amplitude ⊙
    multiple|`` (the time warp's ``ṡ`` never exceeds 1)."""
    return 2.0 * math.pi / ref.period * float(np.linalg.norm(np.multiply(ref.amplitude, ref.multiple)))


def reference_problems(ref: ReferenceConfig, controller: ControllerConfig, where: str) -> list[str]:
    """The reference of ``where`` (``quadrotors.i``) against its controller's limits: its
    extent ``center ± |amplitude|`` inside ``flyable_box``, its speed within ``max_speed``
    (setpoints are clipped to both inside the step, so a reference beyond them would not
    be flown as written)."""
    problems = []
    box = controller.flyable_box
    center, amplitude = np.asarray(ref.center), np.abs(ref.amplitude)
    for k, axis in enumerate("xyz"):
        lo, hi = box.low[k], box.high[k]
        if not lo <= center[k] <= hi:
            problems.append(f"{where}.reference.center: {axis} = {center[k]:g} m is outside the flyable box "
                            f"[{lo:g}, {hi:g}] m (controller.flyable_box)")
        elif center[k] - amplitude[k] < lo or center[k] + amplitude[k] > hi:
            problems.append(f"{where}.reference.amplitude: on {axis} the reference spans "
                            f"[{center[k] - amplitude[k]:g}, {center[k] + amplitude[k]:g}] m, beyond the flyable box "
                            f"[{lo:g}, {hi:g}] m (controller.flyable_box)")
    speed = reference_speed_bound(ref)
    if speed > controller.max_speed:
        problems.append(f"{where}.controller.max_speed: {controller.max_speed:g} m/s, and the reference may reach "
                        f"{speed:.4g} m/s (2π/period · |amplitude ⊙ multiple|): raise max_speed or slow the reference")
    return problems


def _field(setpoint, name):
    if isinstance(setpoint, dict):
        return setpoint.get(name)
    return getattr(setpoint, name, None)


def setpoint_problems(setpoint, quadrotors, where: str = "setpoint") -> list[str]:
    """Problems of a setpoint given on the host (a mapping or an object with
    ``position (n_quads, 3)`` m, ``velocity (n_quads, 3)`` m/s, ``yaw (n_quads,)`` rad;
    any of them may be missing) against the controllers of ``quadrotors`` (a list of
    :class:`QuadrotorConfig`): shapes, finite values, positions inside each flyable box
    and speeds within each ``max_speed``. Each problem names ``where.field.quad``."""
    quads = [q for q in quadrotors if q.controller is not None]
    if not quads:
        return [f"{where}: setpoints need quadrotors with a controller, and there are none"]
    n_q = len(quads)
    problems = []
    values = {}
    for name, shape, unit in (("position", (n_q, 3), "m"), ("velocity", (n_q, 3), "m/s"), ("yaw", (n_q,), "rad")):
        raw = _field(setpoint, name)
        if raw is None:
            continue
        try:
            value = np.asarray(raw, dtype=float)
        except (TypeError, ValueError):
            problems.append(f"{where}.{name}: not an array of numbers ({unit})")
            continue
        if name == "yaw" and value.ndim == 0:
            value = np.full(shape, float(value))
        if value.shape != shape:
            problems.append(f"{where}.{name}: shape {value.shape}, expected {shape} ({unit}, one row per quadrotor)")
            continue
        if not np.isfinite(value).all():
            problems.append(f"{where}.{name}: non-finite values")
            continue
        values[name] = value
    for i, q in enumerate(quads):
        box, ctrl = q.controller.flyable_box, q.controller
        if "position" in values:
            p = values["position"][i]
            for k, axis in enumerate("xyz"):
                if not box.low[k] <= p[k] <= box.high[k]:
                    problems.append(f"{where}.position.{i}: {axis} = {p[k]:g} m is outside the flyable box "
                                    f"[{box.low[k]:g}, {box.high[k]:g}] m (quadrotors.{i}.controller.flyable_box)")
        if "velocity" in values:
            speed = float(np.linalg.norm(values["velocity"][i]))
            if speed > ctrl.max_speed:
                problems.append(f"{where}.velocity.{i}: speed {speed:g} m/s is above max_speed "
                                f"{ctrl.max_speed:g} m/s (quadrotors.{i}.controller.max_speed)")
    return problems


def check_setpoint(setpoint, config, where: str = "setpoint") -> None:
    """Raise :class:`~mysim_jax.config.scene.ConfigError` naming every field of ``setpoint``
    that :func:`setpoint_problems` rejects. ``config``: a SceneConfig, or its list of
    quadrotors. (Inside the step, setpoints beyond the limits are clipped instead.)"""
    quads = config.quadrotors if hasattr(config, "quadrotors") else config
    problems = setpoint_problems(setpoint, quads, where)
    if problems:
        raise ConfigError("invalid setpoint:\n" + "\n".join(f"  {p}" for p in problems))


class GainsFile(StrictModel):
    """A gains file (``scripts/tune_pid.py`` writes one; ``simulate.py --gains`` reads it):
    either one ``controller`` section for every quadrotor, or a ``quadrotors`` list of
    ``{controller: ...}`` by index."""

    class _Controller(StrictModel):
        position: GainSet
        attitude: GainSet

    class _Quad(StrictModel):
        controller: "GainsFile._Controller"

    controller: _Controller | None = None
    quadrotors: list[_Quad] | None = None

    @model_validator(mode="after")
    def _one_form(self):
        if (self.controller is None) == (self.quadrotors is None):
            raise ValueError("give either 'controller' (all quadrotors) or 'quadrotors' (by index)")
        return self


def gain_overrides(gains_path, config_path) -> list[str]:
    """``--set``-style overrides that put the gains of ``gains_path`` into the scene file
    ``config_path``. Raises :class:`~mysim_jax.config.scene.ConfigError` naming the problem."""
    raw_gains = read_yaml_file(gains_path, "gains file")
    raw = read_yaml_file(config_path, "config file")
    if not isinstance(raw_gains, dict):
        raise ConfigError(f"{gains_path}: a gains file must be a YAML mapping at the top level "
                          "('controller:' or 'quadrotors:')")
    try:
        gains = GainsFile.model_validate(raw_gains)
    except ValidationError as err:
        raise ConfigError(f"{gains_path}: invalid gains file\n{format_validation_error(err)}") from None
    n_quads = len(raw.get("quadrotors") or []) if isinstance(raw, dict) else 0
    if n_quads == 0:
        raise ConfigError(f"{gains_path}: the gains file is for quadrotors, and scene {config_path} has none")
    per_quad = [gains.controller] * n_quads if gains.controller is not None else [q.controller for q in gains.quadrotors]
    if len(per_quad) != n_quads:
        raise ConfigError(f"{gains_path}: quadrotors: {len(per_quad)} entries, the scene has {n_quads} quadrotors")
    out = []
    for i, ctrl in enumerate(per_quad):
        for loop in ("position", "attitude"):
            for k in ("kp", "ki", "kd"):
                out.append(f"quadrotors.{i}.controller.{loop}.{k}={list(getattr(getattr(ctrl, loop), k))}")
    return out
