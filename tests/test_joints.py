"""Joint constraints (paper Appendix A) with Baumgarte stabilisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.dynamics.constraints import constraint_error
from mysim_jax.dynamics.quaternion import quat_rotate
from mysim_jax.sim import rollout

pytestmark = pytest.mark.float64

G = 9.81


def _sim(raw, n_steps, every):
    scene, params, state = build(config_from_dict(raw, "test"))
    run = jax.jit(lambda p, s: rollout(scene, p, s, n_steps, every))
    _, traj = run(params, state)
    return scene, params, traj


def _pendulum(theta0, axis, alpha=50.0, beta=50.0, integrator="rk4", dt=1e-3, t_end=10.0):
    """A compound pendulum hanging from a world anchor by a universal joint.

    The anchor's z axis is world x; the body marker's z axis is body y. Tilting about
    world x (axis="x") swings about the anchor axis, tilting about world y about the body
    axis: both are free rotations of a universal joint.
    """
    m, l = 1.3, 0.5
    inertia = [0.011, 0.016, 0.007]
    c, s = np.cos(theta0), np.sin(theta0)
    if axis == "x":
        quat = [np.cos(theta0 / 2), np.sin(theta0 / 2), 0, 0]
        pos = [0.0, l * s, -l * c]
    else:
        quat = [np.cos(theta0 / 2), 0, np.sin(theta0 / 2), 0]
        pos = [-l * s, 0.0, -l * c]
    raw = {
        "name": "pendulum",
        "sim": {"t_end": t_end, "dt": dt, "output_dt": dt, "integrator": integrator, "precision": "float64"},
        "baumgarte": {"alpha": alpha, "beta": beta},
        "anchors": [{"name": "pivot", "pos": [0, 0, 0], "quat": [np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0]}],
        "bodies": [{"name": "bob", "mass": m, "inertia": inertia, "pos": pos, "quat": quat,
                    "markers": [{"name": "top", "pos": [0, 0, l],
                                 "quat": [np.cos(-np.pi / 4), np.sin(-np.pi / 4), 0, 0]}]}],
        "joints": [{"name": "u", "type": "universal", "marker_i": "pivot", "marker_j": "bob.top"}],
    }
    i_pivot = (inertia[0] if axis == "x" else inertia[1]) + m * l * l
    return raw, 2 * np.pi * np.sqrt(i_pivot / (m * G * l))


def _period(t, signal):
    """Mean period from upward zero crossings (linear interpolation)."""
    s = signal - signal.mean()
    idx = np.where((s[:-1] < 0) & (s[1:] >= 0))[0]
    crossings = t[idx] - s[idx] * (t[idx + 1] - t[idx]) / (s[idx + 1] - s[idx])
    return np.diff(crossings).mean(), len(crossings)


@pytest.mark.parametrize("axis", ["x", "y"])
def test_universal_joint_pendulum_small_angle_period(axis):
    theta0 = 0.01
    raw, analytic = _pendulum(theta0, axis)
    scene, params, traj = _sim(raw, 10000, 1)
    t = (np.arange(10000) + 1) * 1e-3
    coord = traj.phys.body_pos[:, 0, 1 if axis == "x" else 0]
    period, n = _period(t, np.asarray(coord))
    assert n >= 5   # period ~1.4 s: six full swings in 10 s
    # finite-amplitude correction is θ0²/16 ≈ 6e-6; the tolerance covers discretisation
    assert abs(period / analytic - 1) < 2e-4, (period, analytic)
    # the motion stays in its plane: the other horizontal coordinate does not move
    other = traj.phys.body_pos[:, 0, 0 if axis == "x" else 1]
    assert np.abs(other).max() < 1e-9


def test_universal_joint_two_axis_swing_keeps_constraint_and_drift_bounded():
    """10 s of large two-axis motion: constraint error bounded (stated bound 1e-7 m)."""
    raw, _ = _pendulum(0.6, "x")
    # also swing about the body's y axis (the marker's z axis): a consistent start needs
    # the COM velocity ω × (COM − pivot) = R_x(0.6) (ω_b × (0, 0, −l)) = (−2 l, 0, 0)
    raw["bodies"][0]["angvel"] = [0.0, 2.0, 0.0]
    raw["bodies"][0]["vel"] = [-1.0, 0.0, 0.0]
    scene, params, traj = _sim(raw, 10000, 10)
    err = jax.vmap(lambda ph: constraint_error(scene, params, ph))(traj.phys)
    assert err.shape == (1000, 4)
    assert np.isfinite(err).all()
    assert np.abs(err).max() < 1e-7, np.abs(err).max()
    # and the joint is not trivially frozen: the bob moves through a large arc
    assert np.ptp(np.asarray(traj.phys.body_pos[:, 0, 1])) > 0.3


def test_baumgarte_pulls_an_initial_violation_back():
    """Start 1 cm off the joint: the error decays (β² C term) instead of persisting."""
    raw, _ = _pendulum(0.0, "x", alpha=20.0, beta=20.0)
    raw["bodies"][0]["pos"] = [0.01, 0.0, -0.5]
    scene, params, traj = _sim(raw, 1000, 10)
    err = np.abs(np.asarray(jax.vmap(lambda ph: constraint_error(scene, params, ph))(traj.phys)))
    assert err[0].max() > 5e-3 and err[-1].max() < 1e-6


def _composite_setup():
    m_a, m_b = 1.0, 0.5
    i_a, i_b = np.diag([0.01, 0.02, 0.025]), np.diag([0.004, 0.002, 0.005])
    p_a, p_b = np.zeros(3), np.array([0.2, 0.1, 0.0])
    com = (m_a * p_a + m_b * p_b) / (m_a + m_b)

    def shift(i, m, d):
        return i + m * (d @ d * np.eye(3) - np.outer(d, d))

    i_c = shift(i_a, m_a, p_a - com) + shift(i_b, m_b, p_b - com)
    omega = np.array([1.0, 2.0, 3.0])
    v_c = np.array([0.1, 0.0, 0.2])
    vel = lambda p: v_c + np.cross(omega, p - com)  # identity attitude: body = world axes
    return m_a, m_b, i_a, i_b, p_a, p_b, com, i_c, omega, v_c, vel


def test_fixed_joint_moves_as_one_rigid_body():
    m_a, m_b, i_a, i_b, p_a, p_b, com, i_c, omega, v_c, vel = _composite_setup()
    sim = {"t_end": 2.0, "dt": 1e-4, "output_dt": 1e-2, "integrator": "rk4", "precision": "float64"}
    pair = {
        "name": "pair", "sim": sim, "gravity": [0, 0, -G],
        "bodies": [
            {"name": "A", "mass": m_a, "inertia": np.diag(i_a).tolist(), "pos": p_a.tolist(),
             "vel": vel(p_a).tolist(), "angvel": omega.tolist(),
             "markers": [{"name": "m", "pos": [0.1, 0.05, 0.0]}]},
            {"name": "B", "mass": m_b, "inertia": np.diag(i_b).tolist(), "pos": p_b.tolist(),
             "vel": vel(p_b).tolist(), "angvel": omega.tolist(),
             "markers": [{"name": "m", "pos": [-0.1, -0.05, 0.0]}]},
        ],
        "joints": [{"name": "weld", "type": "fixed", "marker_i": "A.m", "marker_j": "B.m"}],
    }
    single = {
        "name": "single", "sim": sim, "gravity": [0, 0, -G],
        "bodies": [{"name": "C", "mass": m_a + m_b, "inertia": i_c.tolist(), "pos": com.tolist(),
                    "vel": v_c.tolist(), "angvel": omega.tolist()}],
    }
    _, _, tp = _sim(pair, 20000, 100)
    _, _, ts = _sim(single, 20000, 100)
    q_c = ts.phys.body_quat[:, 0]
    a_expected = ts.phys.body_pos[:, 0] + quat_rotate(q_c, jnp.asarray(p_a - com))
    b_expected = ts.phys.body_pos[:, 0] + quat_rotate(q_c, jnp.asarray(p_b - com))
    assert np.abs(tp.phys.body_pos[:, 0] - a_expected).max() < 1e-7
    assert np.abs(tp.phys.body_pos[:, 1] - b_expected).max() < 1e-7
    # both bodies keep the composite's attitude (quaternions equal up to sign)
    for k in (0, 1):
        dots = np.abs(np.sum(np.asarray(tp.phys.body_quat[:, k] * q_c), axis=-1))
        assert np.abs(dots - 1).max() < 1e-10
    # the motion is non-trivial: the asymmetric body tumbles
    assert np.ptp(np.asarray(q_c), axis=0).max() > 0.5


def test_joint_groups_are_separate_and_batched():
    """Two independent pendulums form two groups of one bucket (no joint coupling)."""
    raw, _ = _pendulum(0.2, "x")
    second = {**raw["bodies"][0], "name": "bob2"}
    raw["bodies"].append(second)
    raw["anchors"].append({**raw["anchors"][0], "name": "pivot2"})
    raw["joints"].append({"name": "u2", "type": "universal", "marker_i": "pivot2", "marker_j": "bob2.top"})
    scene, _, traj = _sim(raw, 500, 50)
    assert len(scene.joint_buckets) == 1 and len(scene.joint_buckets[0].group_bodies) == 2
    np.testing.assert_allclose(traj.phys.body_pos[:, 0], traj.phys.body_pos[:, 1], atol=1e-14)
