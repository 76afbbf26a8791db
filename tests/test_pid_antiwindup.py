"""Anti-windup of the cascaded PID (``mysim_jax/control/pid.py``, step 5), case by case.

The position integrator must not wind up while the controller cannot deliver what it
asks for: while the desired thrust is clipped to ``max_tilt`` (the horizontal force the
position loop wants is not applied) and while any motor saturates. The attitude
integrator holds only while a motor saturates (the tilt limit clips the attitude
*reference*, which the attitude loop can still track). Three hand-built states, one
controller call each, starting from non-zero integrator memory:

* neither limit active: both integrators advance by ``e·dt``;
* tilt-limited, no motor at a limit: the position integrator holds, the attitude one
  advances;
* two of the four motors at ``omega_max`` (a large roll error), tilt limit inactive:
  both hold.

The expected errors (position error, desired attitude from the tilt-limited thrust,
``e_R = ½ (R_dᵀR − RᵀR_d)^∨``) are re-derived in NumPy.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.control.pid import CONTROLLERS, control_time
from mysim_jax.control.setpoint import reference_setpoint

pytestmark = pytest.mark.float64

M, G, DT = 0.28, 9.81, 1e-3
KP, KI, KD = np.array([0.4, 0.4, 1.25]), np.array([0.05, 0.025, 0.05]), np.array([0.2, 0.12, 0.5])
POS0 = np.array([0.0, 0.0, 1.0])
I_POS0 = np.array([0.1, -0.05, 0.02])        # integrator memory before the step (m s)
I_ATT0 = np.array([0.01, -0.02, 0.005])      # (rad s)

_command = jax.jit(lambda scene, p, s: CONTROLLERS["cascaded_pid"].command(
    scene, p, s, reference_setpoint(p, control_time(scene, s.controller))), static_argnums=0)


def _run(center, tilt_rotvec=(0.0, 0.0, 0.0), max_tilt=0.8, omega_max=2440.0):
    """One controller call from the integrator memory above; returns (omega, memory, R)."""
    rot = Rotation.from_rotvec(tilt_rotvec)
    x, y, z, w = rot.as_quat()
    raw = {
        "name": "antiwindup",
        "sim": {"t_end": 1.0, "dt": DT, "output_dt": DT, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": M, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": POS0.tolist(),
                    "quat": [w, x, y, z]}],
        "quadrotors": [{"body": "uav0", "reference": {"center": list(center)},
                        "rotors": {"omega_max": omega_max},
                        "controller": {"max_tilt": max_tilt, "feedforward": "none"}}],
    }
    scene, params, state = build(config_from_dict(raw, "test"))
    memory = state.controller.replace(position_integral=jnp.asarray([I_POS0]), attitude_integral=jnp.asarray([I_ATT0]))
    omega, memory = _command(scene, params, state.replace(controller=memory))
    return np.asarray(omega[0]), memory, rot.as_matrix()


def _expected_errors(center, rot, max_tilt):
    """NumPy: position error, whether the tilt limit clips, attitude error (body at rest)."""
    e = np.asarray(center) - POS0
    force = M * G * np.array([0.0, 0.0, 1.0]) + KP * e + KI * I_POS0
    f_z = max(force[2], 0.1 * M * G)
    horizontal = np.array([force[0], force[1], 0.0])
    h_max = f_z * np.tan(max_tilt)
    tilt_limited = np.linalg.norm(horizontal) > h_max
    if tilt_limited:
        horizontal *= h_max / np.linalg.norm(horizontal)
    force = horizontal + np.array([0.0, 0.0, f_z])
    b3 = force / np.linalg.norm(force)
    b2 = np.cross(b3, [1.0, 0.0, 0.0])                # yaw reference 0
    b2 /= np.linalg.norm(b2)
    rot_d = np.stack([np.cross(b2, b3), b2, b3], axis=1)
    m = rot_d.T @ rot - rot.T @ rot_d
    return e, tilt_limited, 0.5 * np.array([m[2, 1], m[0, 2], m[1, 0]])


def test_no_limit_active_both_integrators_advance():
    center, rotvec = (0.05, -0.03, 1.02), (0.04, -0.03, 0.05)
    omega, memory, rot = _run(center, rotvec)
    e, tilt_limited, e_att = _expected_errors(center, rot, 0.8)
    assert not tilt_limited and np.all(omega < 2440.0) and np.all(omega > 0.0)
    # measured abs error: 0 (bit-identical); tolerance a few ulp of the sums (~0.1), far below
    # the increments e·dt ~ 2e-5..5e-5
    np.testing.assert_allclose(np.asarray(memory.position_integral[0]), I_POS0 + e * DT, rtol=0, atol=1e-17)
    np.testing.assert_allclose(np.asarray(memory.attitude_integral[0]), I_ATT0 + e_att * DT, rtol=0, atol=1e-17)
    assert np.abs(e_att).min() > 1e-3                  # every attitude axis has an error to integrate


def test_tilt_limit_without_motor_saturation_holds_the_position_integrator():
    """3 m to the side with max_tilt = 0.2 rad: the position loop asks for 1.2 N sideways,
    the tilt limit allows 0.55 N; the motors are far from their limits."""
    center, rotvec = (3.0, 0.4, 1.0), (0.0, 0.0, 0.0)
    omega, memory, rot = _run(center, rotvec, max_tilt=0.2)
    e, tilt_limited, e_att = _expected_errors(center, rot, 0.2)
    assert tilt_limited
    assert np.all(omega < 0.9 * 2440.0) and np.all(omega > 0.5 * 2440.0), omega
    np.testing.assert_array_equal(np.asarray(memory.position_integral[0]), I_POS0)
    # measured abs error: 0; increments e_R·dt ~ 3e-6..2e-4 rad s
    np.testing.assert_allclose(np.asarray(memory.attitude_integral[0]), I_ATT0 + e_att * DT, rtol=0, atol=1e-17)
    assert np.abs(e_att[:2]).min() > 1e-2              # the tilt being asked for: ~0.2 rad


def test_one_motor_pair_saturating_holds_both_integrators():
    """Level reference, body rolled 0.5 rad, omega_max = 1450 rad/s: the roll correction
    pushes two motors above the limit while the other two stay below it."""
    center, rotvec = (0.05, -0.03, 1.02), (0.5, 0.0, 0.0)
    omega, memory, rot = _run(center, rotvec, omega_max=1450.0)
    _, tilt_limited, e_att = _expected_errors(center, rot, 0.8)
    assert not tilt_limited and np.abs(e_att).max() > 0.4
    at_limit = np.isclose(omega, 1450.0, rtol=1e-12)
    assert at_limit.sum() == 2 and np.all(omega[~at_limit] < 1445.0), omega
    np.testing.assert_array_equal(np.asarray(memory.position_integral[0]), I_POS0)
    np.testing.assert_array_equal(np.asarray(memory.attitude_integral[0]), I_ATT0)
