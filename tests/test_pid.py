"""Cascaded PID (paper Table PID_controller): gain units, allocation about the CoM,
anti-windup, reference derivatives, and the small maneuver with the paper's gains."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict, load_config
from mysim_jax.control.pid import CONTROLLERS, control_time, flat_body_rates
from mysim_jax.control.setpoint import reference_setpoint
from mysim_jax.control.reference import reference_derivatives, reference_pose
from mysim_jax.tuning.tracking import evaluate_tracking
from mysim_jax.dynamics.quadrotor import allocation_matrix

from conftest import CONFIGS

M, G, C, K, L = 0.28, 9.81, 2.88e-7, 7.24e-9, 0.096


def _raw(units="dyne_cm", feedforward="full", reference=None, **controller):
    return {
        "name": "pid", "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-2, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": M, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [0.0, 0.0, 1.0]}],
        "quadrotors": [{"body": "uav0", "reference": reference or {"center": [0.0, 0.0, 1.0]},
                        "controller": {"attitude_gain_units": units, "feedforward": feedforward, **controller}}],
    }


# compiled once per distinct (hashable) Scene
_controller = jax.jit(lambda scene, p, s: CONTROLLERS["cascaded_pid"].command(
    scene, p, s, reference_setpoint(p, control_time(scene, s.controller))), static_argnums=0)


def _command(scene, params, state):
    omega, memory = _controller(scene, params, state)
    thrust_torque = np.asarray(allocation_matrix(params.quadrotor)[0] @ (omega[0] ** 2))
    return thrust_torque, memory


@pytest.mark.float64
@pytest.mark.parametrize("units, per_unit", [
    ("dyne_cm", (1e-7, 1e-7, 1e-7)),
    ("rotor_speed_squared", (4 * math.sqrt(0.5) * L * C, 4 * math.sqrt(0.5) * L * C, 4 * K)),
    ("torque", (1.0, 1.0, 1.0)),
])
def test_attitude_gain_units(units, per_unit):
    """At hover position with a small attitude error and a body rate, the allocated torque
    is −s ⊙ (kp e_R + kd ω) with the paper's gains and the unit scale s of the reading."""
    gains = {"kp": [7e4, 7e4, 6e4], "ki": [0.0, 0.0, 5e2], "kd": [2e4, 2e4, 1.2e4]}
    if units == "torque":   # SI gains of the same loop (the paper's numbers would saturate)
        gains = {k: [g * 1e-7 for g in v] for k, v in gains.items()}
    raw = _raw(units, "none", attitude=gains)
    rotvec = np.array([0.01, -0.02, 0.03])
    angle = np.linalg.norm(rotvec)
    raw["bodies"][0]["quat"] = [math.cos(angle / 2), *(math.sin(angle / 2) * rotvec / angle)]
    raw["bodies"][0]["angvel"] = [0.2, 0.1, -0.3]
    scene, params, state = build(config_from_dict(raw, "t"))
    wrench, _ = _command(scene, params, state)
    from scipy.spatial.transform import Rotation

    r = Rotation.from_rotvec(rotvec).as_matrix()           # desired attitude is level, yaw 0
    e_r = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    expected = -np.array(per_unit) * (np.array(gains["kp"]) * e_r + np.array(gains["kd"]) * [0.2, 0.1, -0.3])
    np.testing.assert_allclose(wrench[1:], expected, rtol=1e-9)
    # thrust: the weight projected on the tilted body z axis
    np.testing.assert_allclose(wrench[0], M * G * r[2, 2], rtol=1e-9)


@pytest.mark.float64
def test_allocation_about_the_vehicle_centre_of_mass():
    """A 20 g camera 3 cm forward and below: at hover the rotors add r_c × T e_z so the
    vehicle holds level, and the thrust carries the camera too."""
    raw = _raw()
    raw["quadrotors"][0]["cameras"] = [{"name": "cam", "mount": "fixed"}]
    raw["bodies"][0]["pos"] = [0.0, 0.0, 1.0]
    scene, params, state = build(config_from_dict(raw, "t"))
    wrench, _ = _command(scene, params, state)
    m_total = M + 0.02
    r_c = 0.02 * np.array([0.03, 0.0, -0.03]) / m_total
    np.testing.assert_allclose(wrench[0], m_total * G, rtol=1e-12)
    np.testing.assert_allclose(wrench[1:], np.cross(r_c, [0.0, 0.0, m_total * G]), rtol=1e-9, atol=1e-15)


@pytest.mark.float64
def test_anti_windup_freezes_integrators_while_saturated():
    raw = _raw(reference={"center": [0.0, 0.0, 1.02]})
    scene, params, state = build(config_from_dict(raw, "t"))
    _, memory = _command(scene, params, state)            # 2 cm below the reference: integrates
    np.testing.assert_allclose(np.asarray(memory.position_integral[0]), [0.0, 0.0, 0.02 * 1e-3], rtol=1e-12)
    raw = _raw(reference={"center": [0.0, 0.0, 30.0]},    # 29 m below: the motors hit omega_max
               flyable_box={"high": [10.0, 10.0, 40.0]})
    scene, params, state = build(config_from_dict(raw, "t"))
    omega, memory = _controller(scene, params, state)
    np.testing.assert_allclose(np.asarray(omega[0]), 2440.0, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(memory.position_integral), 0.0)
    # and the integrator is clamped to its limit
    state = state.replace(controller=state.controller.replace(position_integral=jnp.asarray([[0.0, 1.9999, 0.0]])))
    raw = _raw(reference={"center": [0.0, 1.0, 1.0]})
    scene, params, _ = build(config_from_dict(raw, "t"))
    _, memory = _controller(scene, params, state)
    np.testing.assert_allclose(np.asarray(memory.position_integral[0, 1]), 2.0, rtol=1e-12)


@pytest.mark.float64
def test_reference_derivatives_and_flat_rates_agree_with_autodiff():
    """Closed-form jerk and snap of the reference, through the ramp and after it, against
    nested forward-mode autodiff; the flatness body rate against a central difference."""
    ref_cfg = {"center": [0.1, -0.2, 1.5], "amplitude": [3.0, 1.5, 0.5], "multiple": [1.0, 2.0, 3.0],
               "phase": [0.3, 0.0, -1.0], "period": 5.0, "ramp": 1.0,
               "yaw": {"center": 0.2, "amplitude": 1.0, "multiple": 2.0, "phase": 0.5}}
    scene, params, _ = build(config_from_dict(_raw(reference=ref_cfg), "t"))
    ref = params.controller.reference

    def nested(f, t, n):
        for _ in range(n):
            f = (lambda g: (lambda u: jax.jvp(g, (u,), (jnp.ones_like(u),))[1]))(f)
        return f(t)

    @jax.jit
    def both(t):
        auto = ([nested(lambda u: reference_pose(ref, u)[0], t, n) for n in range(5)],
                [nested(lambda u: reference_pose(ref, u)[1], t, n) for n in range(3)])
        return reference_derivatives(ref, t), auto

    for t in (1e-4, 0.37, 0.999, 1.0, 2.6, 7.1):   # (at t = 0 autodiff of clip takes half-derivatives)
        closed, auto = both(jnp.asarray(t))
        for a, b in zip(closed[0] + closed[1], auto[0] + auto[1]):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    omega, alpha = jax.jit(flat_body_rates)(params, jnp.asarray(2.6))
    h = 1e-5
    w_plus, _ = jax.jit(flat_body_rates)(params, jnp.asarray(2.6 + h))
    w_minus, _ = jax.jit(flat_body_rates)(params, jnp.asarray(2.6 - h))
    np.testing.assert_allclose(alpha, (w_plus - w_minus) / (2 * h), rtol=1e-6, atol=1e-8)
    assert np.abs(np.asarray(omega)).max() > 0.5


def test_small_maneuver_with_the_paper_gains_tracks_under_5_cm():
    """configs/uav_track_small.yaml: 0.5 m figure-eight at walking pace with yaw, paper gains."""
    config = load_config(CONFIGS / "uav_track_small.yaml")
    scene, params, state = build(config)
    metrics = evaluate_tracking(scene, params, state, config.run_settings())["uav0"]
    assert metrics["rms_position_error_m"] < 0.05, metrics
    # measured 0.37 mm RMS / 0.60 mm max: the flatness feed-forward carries the tracking
    assert metrics["max_position_error_m"] < 0.005, metrics
