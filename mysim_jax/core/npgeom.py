"""Host-side NumPy geometry shared by config checks, the builder and output code.

No JAX here: config validation uses it, and validating a file never imports JAX.
Quaternions are scalar-first ``(w, x, y, z)``, rotating body → world (as everywhere in
the package, :mod:`mysim_jax.dynamics.quaternion`).
"""

from __future__ import annotations

import numpy as np


def rotate(q, v) -> np.ndarray:
    """Rotate ``v`` ``(..., 3)`` by the unit quaternion ``q`` ``(..., 4)`` (broadcasting)."""
    q = np.asarray(q, float)
    v = np.asarray(v, float)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_to_matrix(q) -> np.ndarray:
    """``(..., 4)`` scalar-first quaternions (normalised here) -> ``(..., 3, 3)`` rotation
    matrices, body -> world. The traced twin is :func:`mysim_jax.dynamics.quaternion.quat_to_matrix`."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(m) -> np.ndarray:
    """``(..., 3, 3)`` rotation matrices -> ``(..., 4)`` scalar-first unit quaternions with
    ``w >= 0``. Row ``k`` of the 4 x 4 table below is ``4 q_k q``; the row with the largest
    diagonal entry (the largest ``|q_k|``) is divided out, which stays accurate for every
    rotation (Shepperd's method)."""
    m = np.asarray(m, dtype=float)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    a, b, c = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    d, e, f = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    table = np.stack([
        np.stack([1 + m00 + m11 + m22, a, b, c], -1),
        np.stack([a, 1 + m00 - m11 - m22, d, e], -1),
        np.stack([b, d, 1 - m00 + m11 - m22, f], -1),
        np.stack([c, e, f, 1 - m00 - m11 + m22], -1),
    ], -2)
    k = np.argmax(np.diagonal(table, axis1=-2, axis2=-1), axis=-1)
    q = np.take_along_axis(table, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def skew(v) -> np.ndarray:
    """The matrix ``[v]x`` (3, 3) with ``[v]x w = v x w``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotvec_to_matrix(w) -> np.ndarray:
    """(3, 3) rotation by the rotation vector ``w`` (3,) rad (Rodrigues' formula)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    K = skew(np.asarray(w, float) / th)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
