"""The fixed-step integrators, one step at a time against hand-written updates; sub-steps;
and the unit quaternion over a long float32 run.

The test problem: a point mass on a damped linear spring to an anchor, under gravity
(a nonlinear force in the position: the spring acts along the current direction), and
a free rigid body with asymmetric inertia under a constant world force and a constant
body-frame torque, spinning (Euler's equations ``J ω̇ = τ − ω × Jω``). The accelerations
are re-derived in NumPy; the integrator updates are written out by hand:

* semi-implicit (symplectic) Euler: ``v' = v + h a(x, v)``, ``x' = x + h v'``,
  ``ω'`` from one Newton step of backward Euler on ``J (ω' − ω) + h (ω' × Jω' − τ) = 0``
  (the gyroscopic term implicit), ``q' = q ⊗ exp(½ h ω')`` — and not explicit Euler
  (``x' = x + h v``), which differs by ``h² a``;
* classical RK4 on ``(x, v, p, q, v_b, ω)`` with ``q̇ = ½ q ⊗ (0, ω)``, ``q`` renormalised
  after the step;
* an environment step of ``dt`` with ``substeps: n`` is ``n`` steps of ``dt/n``.
"""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.sim import rollout, step

H = 1e-2
G = np.array([0.0, 0.0, -9.81])
POINT_MASS, K, C, REST = 0.5, 50.0, 0.8, 0.6
ANCHOR = np.array([0.2, -0.1, 1.5])
X0, V0 = np.array([0.9, 0.3, 1.1]), np.array([0.4, -0.7, 0.2])
BODY_MASS, INERTIA = 1.3, np.array([0.02, 0.05, 0.06])
P0, VB0 = np.array([-0.5, 0.2, 0.3]), np.array([0.1, 0.6, -0.3])
Q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])   # w, x, y, z
W0 = np.array([1.5, -2.0, 3.0])
FORCE, TORQUE = np.array([0.3, -0.2, 0.5]), np.array([0.04, -0.03, 0.05])


def _scene(integrator, dt=H, substeps=1):
    raw = {
        "name": "one_step",
        "sim": {"t_end": 1.0, "dt": dt, "substeps": substeps, "output_dt": H, "integrator": integrator,
                "precision": "float64"},
        "gravity": G.tolist(),
        "points": [{"name": "p", "mass": POINT_MASS, "pos": X0.tolist(), "vel": V0.tolist()}],
        "anchors": [{"name": "hook", "pos": ANCHOR.tolist()}],
        "springs": [{"name": "s", "start": "hook", "end": "p", "stiffness": K, "damping": C,
                     "rest_length": REST}],
        "bodies": [{"name": "b", "mass": BODY_MASS, "inertia": INERTIA.tolist(), "pos": P0.tolist(),
                    "quat": Q0.tolist(), "vel": VB0.tolist(), "angvel": W0.tolist()}],
        "loads": [{"at": "b", "force": FORCE.tolist(), "torque": TORQUE.tolist()}],
    }
    return build(config_from_dict(raw, "test"))


def _point_acc(x, v):
    d = x - ANCHOR
    length = np.linalg.norm(d)
    unit = d / length
    return -(K * (length - REST) + C * v @ unit) * unit / POINT_MASS + G


def _body_acc():
    return FORCE / BODY_MASS + G


def _angacc(w):
    return (TORQUE - np.cross(w, INERTIA * w)) / INERTIA


def _quat_mul(p, q):
    pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def _one_step(integrator):
    scene, params, state = _scene(integrator)
    out = jax.jit(lambda s: step(scene, params, s))(state).phys
    return jax.tree.map(lambda a: np.asarray(a)[0], out)


def _same_rotation(q, q_ref):
    return min(np.abs(q - q_ref).max(), np.abs(q + q_ref).max())


@pytest.mark.float64
def test_semi_implicit_euler_step_is_the_symplectic_update():
    out = _one_step("semi_implicit_euler")
    v1 = V0 + H * _point_acc(X0, V0)
    vb1 = VB0 + H * _body_acc()
    # one Newton step on f(w) = J (w - W0) + H (w x J w - torque) = 0, from W0
    J = np.diag(INERTIA)

    def skew(a):
        return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])

    residual = H * (np.cross(W0, J @ W0) - TORQUE)
    w1 = W0 - np.linalg.solve(J + H * (skew(W0) @ J - skew(J @ W0)), residual)
    r0 = Rotation.from_quat(np.roll(Q0, -1))                       # SciPy is scalar-last
    q1 = np.roll((r0 * Rotation.from_rotvec(H * w1)).as_quat(), 1)
    # measured max abs error: 8.3e-17 (velocities, positions), 5.6e-17 (quaternion)
    np.testing.assert_allclose(out.point_vel, v1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.point_pos, X0 + H * v1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.body_vel, vb1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.body_pos, P0 + H * vb1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.body_angvel, w1, rtol=0, atol=1e-15)
    assert _same_rotation(out.body_quat, q1) < 1e-15
    # explicit Euler (positions from the old velocities, attitude from the old rate) is
    # h² a away: 2.3e-3 m (point), 9.4e-4 m (body), 2.0e-4 (quaternion), far outside
    assert np.abs(out.point_pos - (X0 + H * V0)).max() > 1e-4
    assert np.abs(out.body_pos - (P0 + H * VB0)).max() > 1e-4
    q_explicit = np.roll((r0 * Rotation.from_rotvec(H * W0)).as_quat(), 1)
    assert _same_rotation(out.body_quat, q_explicit) > 1e-5
    # and the gyroscopic term is not explicit: that update is 1.5e-3 rad/s away here
    assert np.abs(out.body_angvel - (W0 + H * _angacc(W0))).max() > 1e-4


@pytest.mark.float64
def test_rk4_step_matches_a_hand_written_rk4():
    out = _one_step("rk4")

    def f(y):
        x, v, p, q, vb, w = y
        return (v, _point_acc(x, v), vb, 0.5 * _quat_mul(q, np.concatenate([[0.0], w])), _body_acc(), _angacc(w))

    y0 = (X0, V0, P0, Q0, VB0, W0)
    k1 = f(y0)
    k2 = f(tuple(y + 0.5 * H * k for y, k in zip(y0, k1)))
    k3 = f(tuple(y + 0.5 * H * k for y, k in zip(y0, k2)))
    k4 = f(tuple(y + H * k for y, k in zip(y0, k3)))
    y1 = [y + H / 6 * (a + 2 * b + 2 * c + d) for y, a, b, c, d in zip(y0, k1, k2, k3, k4)]
    y1[3] = y1[3] / np.linalg.norm(y1[3])
    # measured max abs error: 5.6e-17 (all components)
    for got, want in zip((out.point_pos, out.point_vel, out.body_pos, out.body_quat, out.body_vel, out.body_angvel), y1):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
    # a lower-order scheme would be visibly off: one Heun (RK2) step differs by 3.4e-4 m/s
    heun_v = V0 + 0.5 * H * (k1[1] + f(tuple(y + H * k for y, k in zip(y0, k1)))[1])
    assert np.abs(out.point_vel - heun_v).max() > 1e-5


@pytest.mark.float64
@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "rk4"])
def test_substeps_are_steps_of_dt_over_substeps(integrator):
    """One environment step of dt with 4 sub-steps is 4 steps of dt/4."""
    scene, params, state = _scene(integrator, dt=H, substeps=4)
    once = jax.jit(lambda s: step(scene, params, s))(state).phys
    fine, fine_params, fine_state = _scene(integrator, dt=H / 4)
    final, _ = jax.jit(lambda s: rollout(fine, fine_params, s, 4, 4))(fine_state)
    # measured max abs difference: 0 (the same arithmetic)
    for got, want in zip(jax.tree.leaves(once), jax.tree.leaves(final.phys)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-15)
    # and the four sub-steps moved the state (a whole dt, not a quarter of it)
    assert np.abs(np.asarray(once.point_pos) - X0).max() > 1e-3


@pytest.mark.parametrize("integrator", ["rk4", "semi_implicit_euler"])
def test_quaternion_stays_unit_over_a_long_float32_spin(integrator):
    """200 000 steps (200 s) of a torque-free asymmetric body spinning at ~10 rad/s, in
    float32. Neither update preserves |q| in floating point (RK4 not even in exact
    arithmetic; the exponential map of semi-implicit Euler up to round-off), so |q|
    random-walks away from 1 unless it is renormalised after every step."""
    raw = {
        "name": "spin32",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3, "integrator": integrator, "precision": "float32"},
        "gravity": [0.0, 0.0, 0.0],
        "bodies": [{"name": "b", "mass": 1.0, "inertia": INERTIA.tolist(), "quat": Q0.tolist(),
                    "angvel": [0.5, 10.0, 0.3]}],
    }
    scene, params, state = build(config_from_dict(raw, "test"))
    _, traj = jax.jit(lambda s: rollout(scene, params, s, 200_000, 1000))(state)
    q = np.asarray(traj.phys.body_quat[:, 0], dtype=np.float64)
    drift = np.abs(np.linalg.norm(q, axis=1) - 1.0).max()
    # measured max | |q| - 1 |: 7.7e-8 (RK4), 9.4e-8 (semi-implicit Euler); without the
    # renormalisation 1.1e-5 (RK4) and 7.9e-5 (semi-implicit Euler)
    assert drift < 1e-6, drift
    # the spin is real: the attitude sweeps around (not a trivial rest state)
    assert np.ptp(q, axis=0).max() > 1.0


@pytest.mark.float64
def test_semi_implicit_euler_does_not_pump_energy_into_a_free_spin():
    """A torque-free body of unequal moments spinning near its intermediate axis tumbles;
    kinetic energy and |Jω| are conserved exactly. Explicit in the gyroscopic term, the
    semi-implicit Euler step would gain energy every step; implicit in it, it does not."""
    raw = {"name": "spin", "sim": {"t_end": 5.0, "dt": 1e-3, "output_dt": 1e-2, "integrator": "semi_implicit_euler",
                                   "precision": "float64"},
           "gravity": [0, 0, 0],
           "bodies": [{"name": "b", "mass": 1.0, "inertia": INERTIA.tolist(), "angvel": [0.3, 20.0, 0.2]}]}
    scene, params, state = build(config_from_dict(raw, "spin"))
    _, saved = jax.jit(lambda s: rollout(scene, params, s, 5000, 10))(state)
    w = np.asarray(saved.phys.body_angvel[:, 0])
    energy = 0.5 * (w ** 2 * INERTIA).sum(axis=1)
    e0 = 0.5 * (np.array([0.3, 20.0, 0.2]) ** 2 * INERTIA).sum()
    assert np.isfinite(energy).all()
    # measured: the energy never rises above its start (max ratio 1 - 2.9e-7); the step
    # dissipates 7.6 % over 5 s (5000 steps, h ω = 0.02), a first-order damping of the tumble
    assert energy.max() <= e0 * (1 + 1e-9)
    assert energy[-1] > 0.8 * e0
    assert np.ptp(w[:, 1]) > 10.0          # it does tumble (ω_y swings through zero)
