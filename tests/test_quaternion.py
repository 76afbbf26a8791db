"""Quaternion convention: scalar-first, Hamilton, body -> world, body-frame angular velocity."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.dynamics import quaternion as Q

pytestmark = pytest.mark.float64


def _random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return jnp.asarray(q / np.linalg.norm(q, axis=1, keepdims=True))


def test_convention_rotation_about_z_maps_x_to_y():
    q = jnp.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # +90 deg about z
    np.testing.assert_allclose(Q.quat_rotate(q, jnp.array([1.0, 0.0, 0.0])), [0, 1, 0], atol=1e-15)
    # matrix columns are the body axes in the world frame
    np.testing.assert_allclose(Q.quat_to_matrix(q)[:, 0], [0, 1, 0], atol=1e-15)


def test_hamilton_product_ijk():
    i, j, k = jnp.eye(4)[1], jnp.eye(4)[2], jnp.eye(4)[3]
    np.testing.assert_allclose(Q.quat_mul(i, j), k)
    np.testing.assert_allclose(Q.quat_mul(j, i), -k)


def test_rotate_matches_matrix_and_composition():
    q, p = _random_quats(50, 1), _random_quats(50, 2)
    v = jnp.asarray(np.random.default_rng(3).normal(size=(50, 3)))
    np.testing.assert_allclose(Q.quat_rotate(q, v), jnp.einsum("nij,nj->ni", Q.quat_to_matrix(q), v), atol=1e-13)
    np.testing.assert_allclose(Q.quat_rotate(Q.quat_mul(p, q), v), Q.quat_rotate(p, Q.quat_rotate(q, v)), atol=1e-13)
    np.testing.assert_allclose(Q.quat_rotate_inv(q, Q.quat_rotate(q, v)), v, atol=1e-13)


def test_rotvec_roundtrip_and_matrix_roundtrip():
    q = _random_quats(100, 4)
    q = jnp.where(q[:, :1] < 0, -q, q)
    np.testing.assert_allclose(Q.quat_from_rotvec(Q.quat_to_rotvec(q)), q, atol=1e-12)
    np.testing.assert_allclose(Q.quat_from_matrix(Q.quat_to_matrix(q)), q, atol=1e-12)


def test_derivative_is_body_frame_rate():
    """Integrating dq/dt = ½ q⊗ω over a small step equals the exact exponential update."""
    q = _random_quats(10, 5)
    w = jnp.asarray(np.random.default_rng(6).normal(size=(10, 3)))
    h = 1e-6
    fd = (Q.quat_integrate(q, w, h) - Q.quat_integrate(q, w, -h)) / (2 * h)  # central difference
    np.testing.assert_allclose(fd, Q.quat_derivative(q, w), atol=1e-8)
    # body-frame rate: rotating about the body x axis keeps the body x axis fixed in the world
    x_before = Q.quat_rotate(q, jnp.array([1.0, 0, 0]))
    x_after = Q.quat_rotate(Q.quat_integrate(q, jnp.array([0.7, 0, 0]), 0.3), jnp.array([1.0, 0, 0]))
    np.testing.assert_allclose(x_after, x_before, atol=1e-13)


def test_gradients_finite_at_zero_rotation():
    g = jax.jacfwd(Q.quat_from_rotvec)(jnp.zeros(3))
    np.testing.assert_allclose(g, jnp.vstack([jnp.zeros(3), 0.5 * jnp.eye(3)]))
    g2 = jax.grad(lambda v: Q.quat_integrate(jnp.array([1.0, 0, 0, 0]), v, 0.1).sum())(jnp.zeros(3))
    assert np.all(np.isfinite(g2))
    g3 = jax.grad(lambda q: Q.quat_to_rotvec(q).sum())(jnp.array([1.0, 0, 0, 0]))
    assert np.all(np.isfinite(g3))
