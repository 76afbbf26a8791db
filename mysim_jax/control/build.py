"""Host-side assembly of quadrotors, controllers and cameras (called by
:func:`mysim_jax.build.build`; NumPy only, nothing traced).

Cameras (paper Appendix A, Figs. camera_fixed / camera_universal) become ordinary bodies
of the multibody system, joined to their UAV by an ordinary joint, only when a scene
lists them: :func:`expand_cameras` returns a new SceneConfig with, per camera, a body
(placed consistently with the joint), a mount marker ``CAM_mount`` on the UAV, a marker
``mount`` on the camera and a joint ``CAM_joint`` (``fixed`` or ``universal``).

Gimbal marker frames: marker I on the UAV has ``z_I`` = the outer axis and ``x_I`` = the
inner axis at zero angles (UAV frame); marker J on the camera is ``R_nomᵀ R_I R_y(π/2)``
so that ``R_Iᵀ R_J = R_y(π/2)`` at zero angles (see :mod:`mysim_jax.dynamics.gimbal`).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from mysim_jax.config.scene import FIXED_STEP_INTEGRATORS, BodyConfig, ConfigError, JointConfig, MarkerConfig, SceneConfig
from mysim_jax.control.pid import ControlParams, ControlState, PIDGains
from mysim_jax.control.reference import ReferenceParams
from mysim_jax.core.npgeom import matrix_to_quat, quat_to_matrix
from mysim_jax.dynamics.quadrotor import QuadrotorParams, QuadrotorScene
from mysim_jax.dynamics.rotor_layout import allocation_matrix_np, rotor_positions_np
from mysim_jax.dynamics.stability import stable_step

NO_LAG_TIME_CONSTANT = 1e-9   # s: exp(-dt/τ) underflows to 0, the motor follows its command
R_Y_90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def _inertia_matrix(inertia) -> np.ndarray:
    if len(inertia) == 3 and not isinstance(inertia[0], (tuple, list)):
        return np.diag(np.asarray(inertia, dtype=float))
    return np.asarray(inertia, dtype=float)


def rot_z_np(a) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def gimbal_marker_frames(cam) -> tuple[np.ndarray, np.ndarray]:
    """``(R_I in the UAV frame, R_J in the camera frame)`` of a gimbal camera."""
    r_nom = quat_to_matrix(cam.quat)
    z_i = np.asarray(cam.outer_axis, float)
    z_i /= np.linalg.norm(z_i)
    x_i = r_nom @ (np.asarray(cam.inner_axis, float) / np.linalg.norm(cam.inner_axis))
    x_i -= (x_i @ z_i) * z_i
    x_i /= np.linalg.norm(x_i)
    r_i = np.stack([x_i, np.cross(z_i, x_i), z_i], axis=1)
    return r_i, r_nom.T @ r_i @ R_Y_90


def camera_in_uav(cam) -> np.ndarray:
    """Camera orientation in the UAV frame at the start (gimbal: commanded start angles)."""
    r_nom = quat_to_matrix(cam.quat)
    if cam.mount == "fixed":
        return r_nom
    r_i, r_j = gimbal_marker_frames(cam)
    a1, a2 = cam.command.angle
    return r_i @ rot_z_np(a1) @ R_Y_90 @ rot_z_np(a2) @ r_j.T


# --- config expansion ---------------------------------------------------------------


def expand_cameras(config: SceneConfig) -> SceneConfig:
    """A new SceneConfig with every quadrotor camera as a body, two markers and a joint."""
    if not any(q.cameras for q in config.quadrotors):
        return config
    bodies = {b.name: b for b in config.bodies}
    new_bodies, joints = [], list(config.joints)
    for q in config.quadrotors:
        if not q.cameras:
            continue
        uav = bodies[q.body]
        r_uav = quat_to_matrix(uav.quat)
        w_uav = np.asarray(uav.angvel, float)
        mounts = list(uav.markers)
        for cam in q.cameras:
            offset = np.asarray(cam.offset, float)
            r_rel = camera_in_uav(cam)
            if cam.mount == "fixed":
                q_i, q_j = np.asarray(cam.quat, float), np.array([1.0, 0.0, 0.0, 0.0])
            else:
                r_i, r_j = gimbal_marker_frames(cam)
                q_i, q_j = matrix_to_quat(r_i), matrix_to_quat(r_j)
            mounts.append(MarkerConfig(name=f"{cam.name}_mount", pos=tuple(offset), quat=tuple(q_i)))
            new_bodies.append(BodyConfig(
                name=cam.name, mass=cam.mass, inertia=tuple(cam.inertia),
                pos=tuple(np.asarray(uav.pos, float) + r_uav @ offset),
                quat=tuple(matrix_to_quat(r_uav @ r_rel)),
                vel=tuple(np.asarray(uav.vel, float) + r_uav @ np.cross(w_uav, offset)),
                angvel=tuple(r_rel.T @ w_uav),
                markers=[MarkerConfig(name="mount", quat=tuple(q_j))],
            ))
            joints.append(JointConfig(name=f"{cam.name}_joint", type="fixed" if cam.mount == "fixed" else "universal",
                                      marker_i=f"{q.body}.{cam.name}_mount", marker_j=f"{cam.name}.mount"))
        bodies[q.body] = uav.model_copy(update={"markers": mounts})
    all_bodies = [bodies[b.name] for b in config.bodies] + new_bodies
    return config.model_copy(update={"bodies": all_bodies, "joints": joints})


# --- scene, params, state -------------------------------------------------------------------


def _check_servo_stability(config: SceneConfig, bodies) -> None:
    """Reject a gimbal servo too stiff for the fixed step: each axis is a torsional
    spring-damper (kp, kd) between the camera and the UAV, ω² = kp (1/J_cam + 1/J_uav)
    about that axis (at the start attitude)."""
    integrator = config.sim.integrator
    if integrator not in FIXED_STEP_INTEGRATORS or config.sim.substeps == "auto":
        return
    h = config.sim.dt / config.sim.substeps
    for qi, q in enumerate(config.quadrotors):
        j_uav = _inertia_matrix(bodies[q.body].inertia)
        for ci, cam in enumerate(q.cameras):
            if cam.mount != "gimbal":
                continue
            r_rel = camera_in_uav(cam)
            outer = np.asarray(cam.outer_axis, float) / np.linalg.norm(cam.outer_axis)
            inner = r_rel @ (np.asarray(cam.inner_axis, float) / np.linalg.norm(cam.inner_axis))
            j_cam = r_rel @ np.diag(cam.inertia) @ r_rel.T          # UAV frame
            for k, axis in enumerate((outer, inner)):
                inv = 1.0 / (axis @ j_cam @ axis) + 1.0 / (axis @ j_uav @ axis)
                limit = stable_step(integrator, float(np.sqrt(cam.servo.kp[k] * inv)), float(cam.servo.kd[k] * inv))
                if h > limit:
                    raise ConfigError(
                        f"quadrotors.{qi}.cameras.{ci}.servo: axis {k} (kp = {cam.servo.kp[k]:g}, "
                        f"kd = {cam.servo.kd[k]:g}) is stable with {integrator} only below {limit:.3g} s, "
                        f"the step is {h:.3g} s (sim.dt / sim.substeps): soften the servo or use more substeps"
                    )


def _arrays(dtype):
    def arr(x, shape):
        return jnp.asarray(np.asarray(x, dtype=float).reshape(shape), dtype=dtype)
    return arr


def _quadrotor_scene(quads, body_names) -> QuadrotorScene:
    body_index = {n: i for i, n in enumerate(body_names)}
    return QuadrotorScene(
        body=tuple(body_index[q.body] for q in quads),
        controller="none" if quads[0].controller is None else quads[0].controller.type,
        feedforward=tuple(q.controller.feedforward if q.controller else "none" for q in quads),
        attitude_gain_units=tuple(q.controller.attitude_gain_units if q.controller else "torque" for q in quads),
        saturation=tuple(q.controller.saturation if q.controller else "clip" for q in quads),
        thrust_limit=tuple(q.controller.thrust_limit if q.controller else "none" for q in quads),
        descent_limit=tuple(q.controller.descent_limit if q.controller else "none" for q in quads),
        setpoint_mode=quads[0].controller.setpoint_mode if quads[0].controller else "position",
        has_motor_lag=any(q.rotors.time_constant is not None for q in quads),
    )


def _quadrotor_params(quads, arr) -> QuadrotorParams:
    return QuadrotorParams(
        rotor_pos=arr([rotor_positions_np(q.rotors.arm_length, q.rotors.angle) for q in quads], (-1, 4, 3)),
        lift_coefficient=arr([q.rotors.lift_coefficient for q in quads], (-1, 4)),
        torque_coefficient=arr([q.rotors.torque_coefficient for q in quads], (-1, 4)),
        spin=arr([q.rotors.spin for q in quads], (-1, 4)),
        omega_min=arr([q.rotors.omega_min for q in quads], (-1,)),
        omega_max=arr([q.rotors.omega_max for q in quads], (-1,)),
        motor_time_constant=arr([q.rotors.time_constant or NO_LAG_TIME_CONSTANT for q in quads], (-1,)),
    )


def _vehicles(quads, bodies):
    """Each vehicle as the controller sees it, the UAV body plus its cameras: ``(masses,
    centre-of-mass offsets, inertias about the UAV centre)``."""
    masses, com, inertias = [], [], []
    for q in quads:
        uav = bodies[q.body]
        m_cams = sum(c.mass for c in q.cameras)
        m_total = uav.mass + m_cams
        com.append(sum((c.mass * np.asarray(c.offset, float) for c in q.cameras), np.zeros(3)) / m_total)
        masses.append(q.controller.mass if q.controller and q.controller.mass else m_total)
        inertia = _inertia_matrix(uav.inertia)
        for c in q.cameras:   # about the UAV centre, cameras at their start attitude
            r, d = camera_in_uav(c), np.asarray(c.offset, float)
            inertia = inertia + r @ np.diag(c.inertia) @ r.T + c.mass * (d @ d * np.eye(3) - np.outer(d, d))
        inertias.append(inertia)
    return masses, com, inertias


def _hover_speeds(quads, masses, com, gravity: float) -> list[np.ndarray]:
    """Motor speeds that hold each vehicle (hover allocation): the motors start there."""
    speeds = []
    for q, m, r_c in zip(quads, masses, com):
        r = q.rotors
        alloc = allocation_matrix_np(r.arm_length, r.angle, r.lift_coefficient, r.torque_coefficient, r.spin)
        thrust = m * gravity
        wrench = np.concatenate([[thrust], np.cross(r_c, [0.0, 0.0, thrust])])
        sq = np.clip(np.linalg.solve(alloc, wrench), r.omega_min ** 2, r.omega_max ** 2)
        speeds.append(np.sqrt(sq))
    return speeds


def _control_params(quads, masses, com, inertias, arr) -> ControlParams:
    refs = [q.reference for q in quads]
    reference = None
    if refs[0] is not None:     # every quadrotor has a reference or none has (config check)
        reference = ReferenceParams(
            center=arr([r.center for r in refs], (-1, 3)),
            amplitude=arr([r.amplitude for r in refs], (-1, 3)),
            multiple=arr([r.multiple for r in refs], (-1, 3)),
            phase=arr([r.phase for r in refs], (-1, 3)),
            period=arr([r.period for r in refs], (-1,)),
            ramp=arr([r.ramp for r in refs], (-1,)),
            yaw_center=arr([r.yaw.center for r in refs], (-1,)),
            yaw_amplitude=arr([r.yaw.amplitude for r in refs], (-1,)),
            yaw_multiple=arr([r.yaw.multiple for r in refs], (-1,)),
            yaw_phase=arr([r.yaw.phase for r in refs], (-1,)),
        )
    return ControlParams(
        gains=PIDGains(**{
            f"{loop}_{k}": arr([getattr(getattr(q.controller, loop), k) for q in quads], (-1, 3))
            for loop in ("position", "attitude") for k in ("kp", "ki", "kd")
        }),
        mass=arr(masses, (-1,)),
        com_offset=arr(com, (-1, 3)),
        inertia=arr(inertias, (-1, 3, 3)),
        max_tilt=arr([q.controller.max_tilt for q in quads], (-1,)),
        position_integral_limit=arr([q.controller.position_integral_limit for q in quads], (-1,)),
        attitude_integral_limit=arr([q.controller.attitude_integral_limit for q in quads], (-1,)),
        box_low=arr([q.controller.flyable_box.low for q in quads], (-1, 3)),
        box_high=arr([q.controller.flyable_box.high for q in quads], (-1, 3)),
        max_speed=arr([q.controller.max_speed for q in quads], (-1,)),
        reference=reference,
    )


def build_quadrotors(config: SceneConfig, body_names, dtype):
    """``(QuadrotorScene, QuadrotorParams, ControlParams | None, ControlState)`` or all None.

    ``config`` must already be expanded (:func:`expand_cameras`). Wind, body drag and the
    gimbals' servos are effects that build themselves (:mod:`mysim_jax.effects.wind`,
    :mod:`mysim_jax.effects.body_drag`, :mod:`mysim_jax.effects.gimbal_servo`).
    """
    quads = config.quadrotors
    if not quads:
        return None, None, None, None
    bodies = {b.name: b for b in config.bodies}
    _check_servo_stability(config, bodies)
    arr = _arrays(dtype)
    qs = _quadrotor_scene(quads, body_names)
    qp = _quadrotor_params(quads, arr)
    masses, com, inertias = _vehicles(quads, bodies)
    speeds = _hover_speeds(quads, masses, com, float(np.linalg.norm(config.gravity)))
    n_q = len(quads)
    memory = ControlState(
        position_integral=arr(np.zeros((n_q, 3)), (-1, 3)),
        attitude_integral=arr(np.zeros((n_q, 3)), (-1, 3)),
        motor_speed=arr(speeds, (-1, 4)),
        motor_command=arr(speeds, (-1, 4)),
        steps=jnp.zeros((), dtype=jnp.int32),
    )
    if qs.controller == "none":
        return qs, qp, None, memory
    return qs, qp, _control_params(quads, masses, com, inertias, arr), memory
