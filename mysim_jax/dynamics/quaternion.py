"""Unit quaternions for rigid-body attitude.

Convention (used everywhere in mysim_jax):

* scalar-first ``q = (w, x, y, z)``;
* Hamilton product (``i*j = k``);
* ``q`` rotates vectors from the **body** frame into the **world** frame:
  ``v_world = q ⊗ (0, v_body) ⊗ q*`` (``quat_rotate``), so ``quat_to_matrix(q)`` has the
  body axes as its columns;
* angular velocity ``omega`` is expressed in the **body** frame, so the kinematics are
  ``dq/dt = ½ q ⊗ (0, omega)`` (``quat_derivative``) and the exact update over a step with
  constant body rate is ``q ⊗ exp(½ omega h)`` (``quat_integrate``).

All functions act on the last axis and broadcast over leading axes. Every function is
finite in value and gradient at zero rotation (``quat_from_rotvec(0)``) and for
non-normalised inputs of ``quat_normalize`` away from zero.
"""

from __future__ import annotations

import jax.numpy as jnp

from mysim_jax.core import vecmath


def quat_mul(p, q):
    """Hamilton product ``p ⊗ q``: ``(..., 4), (..., 4) -> (..., 4)``."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conj(q):
    """Conjugate (the inverse of a unit quaternion)."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_normalize(q):
    """Scale to unit norm."""
    n = jnp.sqrt(q[..., 0] ** 2 + q[..., 1] ** 2 + q[..., 2] ** 2 + q[..., 3] ** 2)
    return q / n[..., None]


def quat_rotate(q, v):
    """Rotate body-frame vectors into the world frame: ``R(q) v``."""
    w = q[..., 0]
    u = q[..., 1:]
    t = 2.0 * vecmath.cross(u, v)
    return v + w[..., None] * t + vecmath.cross(u, t)


def quat_rotate_inv(q, v):
    """Rotate world-frame vectors into the body frame: ``R(q)^T v``."""
    w = q[..., 0]
    u = -q[..., 1:]
    t = 2.0 * vecmath.cross(u, v)
    return v + w[..., None] * t + vecmath.cross(u, t)


def quat_to_matrix(q):
    """Rotation matrix ``(..., 3, 3)``; its columns are the body axes in the world frame."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    row0 = jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    row1 = jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    row2 = jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return jnp.stack([row0, row1, row2], axis=-2)


def quat_from_rotvec(rotvec):
    """Quaternion of a rotation by angle ``|rotvec|`` about ``rotvec``: ``exp(½ rotvec)``.

    Uses a Taylor expansion below 1e-4 rad so value and gradient are exact at zero.
    """
    angle_sq = vecmath.dot(rotvec, rotvec)
    small = angle_sq < 1e-8
    safe_sq = jnp.where(small, 1.0, angle_sq)
    angle = jnp.sqrt(safe_sq)
    half = 0.5 * angle
    w = jnp.where(small, 1.0 - angle_sq / 8.0, jnp.cos(half))
    scale = jnp.where(small, 0.5 - angle_sq / 48.0, jnp.sin(half) / angle)
    return jnp.concatenate([w[..., None], scale[..., None] * rotvec], axis=-1)


def quat_to_rotvec(q):
    """Inverse of ``quat_from_rotvec`` (shortest rotation, angle in [0, π])."""
    q = jnp.where(q[..., :1] < 0.0, -q, q)
    vec = q[..., 1:]
    s_sq = vecmath.dot(vec, vec)
    small = s_sq < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, s_sq))
    angle = 2.0 * jnp.arctan2(s, q[..., 0])
    scale = jnp.where(small, 2.0 / q[..., 0], angle / s)
    return scale[..., None] * vec


def quat_derivative(q, omega_body):
    """Time derivative ``dq/dt = ½ q ⊗ (0, omega_body)``."""
    omega_q = jnp.concatenate([jnp.zeros_like(omega_body[..., :1]), omega_body], axis=-1)
    return 0.5 * quat_mul(q, omega_q)


def quat_integrate(q, omega_body, h):
    """Exact attitude update for a constant body rate over ``h``, renormalised."""
    return quat_normalize(quat_mul(q, quat_from_rotvec(omega_body * h)))


def quat_from_matrix(m):
    """Quaternion (w >= 0) from a rotation matrix, NumPy-free and branch-free (Shepperd)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    cands = jnp.stack(
        [
            jnp.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                       m[..., 1, 0] - m[..., 0, 1]], -1),
            jnp.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22,
                       m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            jnp.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                       1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            jnp.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                       m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    diag = jnp.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = jnp.argmax(diag, axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = quat_normalize(q)
    return jnp.where(q[..., :1] < 0.0, -q, q)
