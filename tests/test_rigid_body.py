"""Free rigid bodies: Newton-Euler + quaternion kinematics against an independent solution."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.dynamics.quaternion import quat_rotate
from mysim_jax.sim import rollout

pytestmark = pytest.mark.float64

INERTIA = np.array([0.02, 0.05, 0.06])
OMEGA0 = np.array([0.1, 4.0, 0.2])   # near the intermediate axis: the tennis-racket flip


def _scene(integrator, dt):
    return {
        "name": "tumbler",
        "sim": {"t_end": 5.0, "dt": dt, "output_dt": 0.1, "integrator": integrator, "precision": "float64"},
        "gravity": [0, 0, -9.81],
        "bodies": [{"name": "b", "mass": 0.7, "inertia": INERTIA.tolist(), "vel": [1.0, 0.0, 3.0],
                    "angvel": OMEGA0.tolist(), "quat": [0.9, 0.1, -0.3, 0.2]}],
    }


def _scipy_reference(times, q0):
    """Euler's equations in the body frame + rotation matrix kinematics, DOP853."""

    def rhs(_, y):
        w, r = y[:3], y[3:].reshape(3, 3)
        dw = (np.cross(INERTIA * w, w)) / INERTIA
        return np.concatenate([dw, (r @ np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])).ravel()])

    r0 = Rotation.from_quat([q0[1], q0[2], q0[3], q0[0]]).as_matrix()
    sol = solve_ivp(rhs, (0, times[-1]), np.concatenate([OMEGA0, r0.ravel()]), method="DOP853",
                    t_eval=times, rtol=1e-12, atol=1e-12)
    return sol.y[:3].T, sol.y[3:].T.reshape(-1, 3, 3)


@pytest.mark.parametrize("integrator, dt, tol", [("rk4", 1e-3, 1e-8), ("semi_implicit_euler", 1e-4, 2e-2)])
def test_torque_free_tumbling_matches_scipy(integrator, dt, tol):
    scene, params, state = build(config_from_dict(_scene(integrator, dt), "t"))
    every = int(round(0.1 / dt))
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, 50 * every, every))(params, state)
    times = np.arange(1, 51) * 0.1
    w_ref, r_ref = _scipy_reference(np.concatenate([[0.0], times]), np.asarray(state.phys.body_quat[0]))
    w = np.asarray(traj.phys.body_angvel[:, 0])
    assert np.abs(w - w_ref[1:]).max() < tol * np.abs(OMEGA0).max()
    # body x axis in the world
    x_axis = np.asarray(quat_rotate(traj.phys.body_quat[:, 0], jnp.array([1.0, 0, 0])))
    assert np.abs(x_axis - r_ref[1:, :, 0]).max() < 10 * tol
    # the flip happens (the motion is not trivially near the initial state)
    assert w[:, 1].min() < 0 < w[:, 1].max()
    # the centre of mass is a projectile
    pos = np.asarray(traj.phys.body_pos[:, 0])
    np.testing.assert_allclose(pos[:, 2], 3.0 * times - 0.5 * 9.81 * times**2, atol=5e-3 if integrator != "rk4" else 1e-9)


def test_angular_momentum_and_energy_conserved_rk4():
    scene, params, state = build(config_from_dict(_scene("rk4", 1e-3), "t"))
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, 5000, 10))(params, state)
    w = np.asarray(traj.phys.body_angvel[:, 0])
    l_world = np.asarray(quat_rotate(traj.phys.body_quat[:, 0], jnp.asarray(INERTIA * w)))
    l0 = INERTIA * OMEGA0
    l0_world = np.asarray(quat_rotate(state.phys.body_quat[0], jnp.asarray(l0)))
    assert np.abs(l_world - l0_world).max() < 1e-9 * np.linalg.norm(l0)
    energy = 0.5 * np.sum(INERTIA * w * w, axis=1)
    assert np.abs(energy / (0.5 * np.sum(INERTIA * OMEGA0**2)) - 1).max() < 1e-9
