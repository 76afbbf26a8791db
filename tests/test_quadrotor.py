"""Quadrotor model (paper Sec. 2.2, Table UAV_model): allocation, rotor forces, motors,
aerodynamics, config errors, and the hover the controller holds."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict, load_config
from mysim_jax.control.pid import CONTROLLERS
from mysim_jax.control.setpoint import reference_setpoint
from mysim_jax.dynamics.quadrotor import allocation_inverse, allocation_matrix, motor_response, rotor_wrench
from mysim_jax.effects.wind import WIND, wind_force
from mysim_jax.sim import rollout

from conftest import CONFIGS

M, G, C, K, L = 0.28, 9.81, 2.88e-7, 7.24e-9, 0.096
INERTIA = np.array([1.40e-4, 1.40e-4, 2.17e-4])


def _uav(controller=True, **quad):
    q = {"body": "uav0", **quad}
    if controller:
        q.setdefault("reference", {"center": [0.0, 0.0, 1.0]})
    else:
        q["controller"] = None
    return {
        "name": "uav", "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-2, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": M, "inertia": INERTIA.tolist(), "pos": [0.0, 0.0, 1.0]}],
        "quadrotors": [q],
    }


@pytest.mark.float64
def test_allocation_is_the_papers_and_inverts():
    scene, params, _ = build(config_from_dict(_uav(), "t"))
    alloc = np.asarray(allocation_matrix(params.quadrotor)[0])
    h = math.sqrt(2) / 2 * L * C
    paper = np.array([
        [C, C, C, C],
        [h, -h, -h, h],          # τ_θ = (√2/2) l c (ω1² − ω2² − ω3² + ω4²), about body x
        [-h, -h, h, h],          # −τ_φ: the paper's φ axis is body −y (d_i = l [sin θ, cos θ, 0])
        [K, -K, K, -K],          # τ_ψ = k (ω1² − ω2² + ω3² − ω4²)
    ])
    np.testing.assert_allclose(alloc, paper, rtol=1e-12, atol=1e-22)
    inv = np.asarray(allocation_inverse(params.quadrotor)[0])
    np.testing.assert_allclose(inv @ alloc, np.eye(4), atol=1e-10)


@pytest.mark.float64
def test_rotor_wrench_equals_arm_cross_products():
    """Thrust and torque from the allocation matrix against Σ d_i × F_i + spin_i k ω_i² z."""
    angles = [0.7, 2.5, 3.8, 5.6]                       # an irregular layout on purpose
    arms = [0.09, 0.1, 0.11, 0.095]
    scene, params, _ = build(config_from_dict(_uav(rotors={"angle": angles, "arm_length": arms}), "t"))
    speed_sq = np.array([1.1e6, 2.3e6, 1.9e6, 2.7e6])
    thrust, torque = (np.asarray(x[0]) for x in rotor_wrench(params.quadrotor, jnp.asarray(speed_sq)[None]))
    d = np.stack([np.array(arms) * np.sin(angles), np.array(arms) * np.cos(angles), np.zeros(4)], axis=1)
    forces = np.stack([np.zeros(4), np.zeros(4), C * speed_sq], axis=1)
    expected = np.cross(d, forces).sum(axis=0) + np.array([0, 0, 1.0]) * (K * speed_sq * [1, -1, 1, -1]).sum()
    np.testing.assert_allclose(thrust, C * speed_sq.sum(), rtol=1e-13)
    np.testing.assert_allclose(torque, expected, rtol=1e-12, atol=1e-18)


@pytest.mark.float64
def test_free_flight_under_fixed_motor_speeds_matches_scipy():
    """Open loop (no controller), unequal motor speeds: the body climbs, tilts and spins.
    Reference: Newton-Euler + rotation-matrix kinematics written here, SciPy DOP853."""
    raw = _uav(controller=False)
    raw["bodies"][0]["angvel"] = [0.3, -0.2, 0.5]
    scene, params, state = build(config_from_dict(raw, "t"))
    omega = np.array([1700.0, 1500.0, 1650.0, 1560.0])
    n = 1000
    with pytest.raises(ValueError, match="without a controller: pass the motor commands"):
        rollout(scene, params, state, 1)
    from mysim_jax.sim import step

    def body(s, _):
        return step(scene, params, s, jnp.asarray(omega)[None]), s.phys.body_pos

    final, _ = jax.jit(lambda s: jax.lax.scan(body, s, None, length=n))(state)

    d = np.stack([L * np.sin(np.arange(4) * np.pi / 2 + np.pi / 4), L * np.cos(np.arange(4) * np.pi / 2 + np.pi / 4),
                  np.zeros(4)], axis=1)
    f_body = np.array([0.0, 0.0, C * (omega ** 2).sum()])
    tau = np.cross(d, np.stack([np.zeros(4), np.zeros(4), C * omega ** 2], 1)).sum(0)
    tau[2] += K * (omega ** 2 * [1, -1, 1, -1]).sum()

    def rhs(_, y):
        r = y[6:15].reshape(3, 3)
        w = y[15:]
        acc = r @ f_body / M + np.array([0, 0, -G])
        dw = (tau - np.cross(w, INERTIA * w)) / INERTIA
        wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.concatenate([y[3:6], acc, (r @ wx).ravel(), dw])

    y0 = np.concatenate([[0, 0, 1.0], np.zeros(3), np.eye(3).ravel(), [0.3, -0.2, 0.5]])
    sol = solve_ivp(rhs, (0, n * 1e-3), y0, method="DOP853", rtol=1e-12, atol=1e-12)
    ref_pos, ref_rot = sol.y[:3, -1], sol.y[6:15, -1].reshape(3, 3)
    assert np.abs(ref_pos - [0, 0, 1]).max() > 0.3                  # it really moves
    np.testing.assert_allclose(np.asarray(final.phys.body_pos[0]), ref_pos, atol=1e-9)
    q = np.asarray(final.phys.body_quat[0])
    rot = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    np.testing.assert_allclose(rot, ref_rot, atol=1e-8)             # RK4 at 1 ms: ~3e-9 measured
    assert np.arccos((np.trace(ref_rot) - 1) / 2) > 0.3              # and it really turns


@pytest.mark.float64
def test_motor_lag_is_the_exact_first_order_response():
    raw = _uav(rotors={"time_constant": 0.03})
    scene, params, _ = build(config_from_dict(raw, "t"))
    qp, dt, tau = params.quadrotor, 1e-3, 0.03
    w0, cmd = np.array([[1500.0, 1600.0, 1400.0, 1550.0]]), np.array([[2000.0, 1000.0, 3000.0, 1550.0]])
    end, mean_sq = motor_response(jnp.asarray(cmd), jnp.asarray(w0), qp, dt, True)
    clipped = np.minimum(cmd, 2440.0)                                # the 3000 rad/s command is clipped
    exact = clipped + (w0 - clipped) * np.exp(-dt / tau)
    np.testing.assert_allclose(np.asarray(end), exact, rtol=1e-13)
    for i in range(4):
        integral = quad(lambda t: (clipped[0, i] + (w0[0, i] - clipped[0, i]) * np.exp(-t / tau)) ** 2, 0, dt,
                        epsabs=0, epsrel=1e-13)[0]
        np.testing.assert_allclose(float(mean_sq[0, i]), integral / dt, rtol=1e-11)
    # without lag the motors apply the clipped command
    end, mean_sq = motor_response(jnp.asarray(cmd), jnp.asarray(w0), qp, dt, False)
    np.testing.assert_allclose(np.asarray(mean_sq), clipped ** 2, rtol=1e-14)


@pytest.mark.float64
def test_drag_and_wind_give_the_analytic_terminal_velocity():
    """Motors off, no gravity: a constant wind force F against linear drag D gives
    v(t) = F/D (1 − exp(−D t / m)) along the wind."""
    raw = _uav(controller=False, drag=[0.5, 0.5, 0.8], wind={"force": [1.0, -0.5, 0.0]},
               rotors={"omega_min": 0.0})
    raw["gravity"] = [0.0, 0.0, 0.0]
    scene, params, state = build(config_from_dict(raw, "t"))
    from mysim_jax.sim import step

    def body(s, _):
        s = step(scene, params, s, jnp.zeros((1, 4)))
        return s, s.phys.body_vel[0]

    _, vel = jax.jit(lambda s: jax.lax.scan(body, s, None, length=1000))(state)
    t = np.arange(1, 1001) * 1e-3
    expected = np.outer(1 - np.exp(-0.5 * t / M), np.array([1.0, -0.5, 0.0]) / 0.5)
    np.testing.assert_allclose(np.asarray(vel), expected, atol=1e-10)
    # a 1 − cos gust: zero outside its window, its peak at mid-window
    raw = _uav(controller=False, wind={"gust_force": [0.0, 2.0, 0.0], "gust_start": 1.0, "gust_duration": 0.5})
    _, params, _ = build(config_from_dict(raw, "t"))
    forces = np.array([np.asarray(wind_force(WIND.params(params), t))[0, 1] for t in (0.9, 1.0, 1.125, 1.25, 1.6)])
    np.testing.assert_allclose(forces, [0.0, 0.0, 1.0, 2.0, 0.0], atol=1e-12)


@pytest.mark.float64
def test_hover_speed_is_analytic():
    """At the hover point the controller commands sqrt(m g / (4 c)) on every motor."""
    scene, params, state = build(config_from_dict(_uav(), "t"))
    command = CONTROLLERS["cascaded_pid"].command
    omega, _ = jax.jit(lambda p, s: command(scene, p, s, reference_setpoint(p, 0.0)))(params, state)
    analytic = math.sqrt(M * G / (4 * C))
    assert abs(analytic - 1544.14) < 0.01
    np.testing.assert_allclose(np.asarray(omega[0]), analytic, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(state.controller.motor_speed[0]), analytic, rtol=1e-6)


def test_hover_holds_position_for_10_s():
    """configs/uav_hover.yaml (float32, RK4): 10 s within 1 mm, no drift, motors at hover."""
    scene, params, state = build(load_config(CONFIGS / "uav_hover.yaml"))
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, 10000, 10))(params, state)
    pos = np.asarray(traj.phys.body_pos[:, 0], dtype=np.float64)
    dev = np.linalg.norm(pos - [0.0, 0.0, 1.0], axis=1)
    assert np.isfinite(dev).all() and dev.max() < 1e-3, dev.max()
    t = np.arange(1, 1001) * 1e-2
    late = t > 5.0
    slope = np.polyfit(t[late], pos[late], 1)[0]                    # m/s per axis over the last 5 s
    assert np.abs(slope).max() < 1e-5, slope
    assert np.abs(np.asarray(traj.phys.body_vel[-1, 0])).max() < 1e-4
    omega = np.asarray(traj.controller.motor_command[:, 0])
    np.testing.assert_allclose(omega, math.sqrt(M * G / (4 * C)), rtol=1e-4)


@pytest.mark.parametrize("patch, field", [
    ({"rotors": {"arm_length": [0.096, -0.096, 0.096, 0.096]}}, "quadrotors.0.rotors.arm_length.1"),
    ({"rotors": {"lift_coefficient": [2.88e-7, 2.88e-7, 2.88e-7]}}, "quadrotors.0.rotors.lift_coefficient"),
    ({"rotors": {"omega_max": 1000.0, "omega_min": 1200.0}}, "omega_min (1200) must be below omega_max"),
    ({"rotors": {"spin": [1, 1, 1, 1]}}, "singular allocation matrix"),
    ({"rotors": {"spin": [1, 2, 1, -1]}}, "quadrotors.0.rotors.spin.1"),
    ({"body": "uav9"}, "quadrotors.0.body: 'uav9' is not a body"),
    ({"controller": {"position": {"kp": [1, 2], "ki": [0, 0, 0], "kd": [0, 0, 0]}}},
     "quadrotors.0.controller.position.kp"),
    ({"controller": {"attitude": {"kp": [1, 2, -3], "ki": [0, 0, 0], "kd": [0, 0, 0]}}},
     "quadrotors.0.controller.attitude.kp.2"),
    ({"controller": {"attitude_gain_units": "furlongs"}}, "quadrotors.0.controller.attitude_gain_units"),
    ({"controller": {"max_tilt": 2.0}}, "quadrotors.0.controller.max_tilt"),
    ({"reference": {"center": [0, 0, 1], "period": 0}}, "quadrotors.0.reference.period"),
    ({"drag": [0.1, -0.1, 0.1]}, "quadrotors.0.drag.1"),
    ({"cameras": [{"name": "uav0", "mount": "fixed"}]}, "quadrotors.0.cameras.0.name: 'uav0' is already used"),
    ({"cameras": [{"name": "c", "mount": "gimbal", "outer_axis": [0, 0, 1], "inner_axis": [0, 0, 1]}]},
     "must be perpendicular"),
    ({"cameras": [{"name": "c", "mount": "fixed", "servo": {"kp": [1, 1], "kd": [0.1, 0.1]}}]},
     "servo: only a gimbal camera has these"),
    ({"cameras": [{"name": "c", "mount": "fixed", "mass": -0.02}]}, "quadrotors.0.cameras.0.mass"),
    ({"rotor": {}}, "quadrotors.0.rotor: unknown key"),
])
def test_bad_quadrotor_config_names_the_field(patch, field):
    raw = _uav()
    raw["quadrotors"][0].update(patch)
    with pytest.raises(ConfigError) as info:
        config_from_dict(raw, "uav.yaml")
    assert field in str(info.value), str(info.value)


def test_every_quadrotor_or_none_has_a_controller():
    raw = _uav()
    raw["bodies"].append({**raw["bodies"][0], "name": "uav1"})
    raw["quadrotors"].append({"body": "uav1", "controller": None})
    with pytest.raises(ConfigError, match="quadrotors.0.controller: either every quadrotor has a controller"):
        config_from_dict(raw, "uav.yaml")


def test_too_stiff_gimbal_servo_is_rejected_before_compiling():
    raw = _uav(cameras=[{"name": "cam", "mount": "gimbal", "servo": {"kp": [0.02, 200.0], "kd": [5e-4, 5e-4]}}])
    cfg = config_from_dict(raw, "uav.yaml")
    with jax.enable_x64(True), pytest.raises(ConfigError, match=r"quadrotors.0.cameras.0.servo: axis 1 .* stable"):
        build(cfg)
