"""Small 3-vector helpers, written component-wise and safe under autodiff.

Arrays hold 3-vectors on their last axis (``(..., 3)``). The helpers spell out the
three components instead of reducing over a size-3 minor axis, which keeps XLA's loops
vectorised over the batch under ``jax.vmap``. Whether that is faster than a reduction
depends on the host (BENCHMARKS.md, section f, times both side by side).
"""

from __future__ import annotations

import jax.numpy as jnp


def dot(a, b):
    """Dot product over the last axis: ``(..., 3), (..., 3) -> (...)``."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a, b):
    """Cross product over the last axis: ``(..., 3), (..., 3) -> (..., 3)``."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def safe_norm(v, tiny: float = 1e-30):
    """Euclidean norm over the last axis, 0 at v = 0 with a finite (zero) gradient there.

    Uses the double-``where`` trick so that neither the value nor the gradient is NaN when
    ``v`` is exactly zero (a collapsed rope segment, coincident sphere centres).
    """
    sq = dot(v, v)
    positive = sq > tiny
    safe_sq = jnp.where(positive, sq, 1.0)
    return jnp.where(positive, jnp.sqrt(safe_sq), 0.0)


def safe_unit(v, tiny: float = 1e-30):
    """Return ``(norm, unit vector)``; the unit vector is 0 where ``v`` is 0 (finite grads)."""
    n = safe_norm(v, tiny)
    denom = jnp.where(n > 0.0, n, 1.0)
    return n, v / denom[..., None]


def skew(v):
    """Cross-product matrix ``(..., 3, 3)`` of ``v`` ``(..., 3)``: ``skew(a) @ b = a × b``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                      jnp.stack([-y, x, zero], -1)], axis=-2)


def _adjugate3(a):
    """Rows of the adjugate (transposed cofactors) of ``a`` ``(..., 3, 3)`` and its determinant."""
    a00, a01, a02 = a[..., 0, 0], a[..., 0, 1], a[..., 0, 2]
    a10, a11, a12 = a[..., 1, 0], a[..., 1, 1], a[..., 1, 2]
    a20, a21, a22 = a[..., 2, 0], a[..., 2, 1], a[..., 2, 2]
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    adj = ((c00, a02 * a21 - a01 * a22, a01 * a12 - a02 * a11),
           (c01, a00 * a22 - a02 * a20, a02 * a10 - a00 * a12),
           (c02, a01 * a20 - a00 * a21, a00 * a11 - a01 * a10))
    return adj, det


def inv3(a):
    """Inverse of 3 x 3 matrices ``(..., 3, 3)`` by the adjugate over the determinant.

    Written out element by element (no factorisation primitive), so it vectorises over any
    batch layout; for the well-conditioned matrices it is used on (inertia tensors) it
    agrees with an LU inverse to round-off.
    """
    adj, det = _adjugate3(a)
    inv_det = 1.0 / det
    return jnp.stack([jnp.stack([x * inv_det for x in row], axis=-1) for row in adj], axis=-2)


def solve3(a, b):
    """Solve ``a x = b`` for 3 x 3 systems: ``(..., 3, 3), (..., 3) -> (..., 3)``.

    Cramer's rule (the adjugate over the determinant, as :func:`inv3`): for the small,
    well-conditioned systems it is used on (a body's inertia plus a step-sized correction)
    it agrees with an LU solve to round-off.
    """
    adj, det = _adjugate3(a)
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([r0 * b0 + r1 * b1 + r2 * b2 for r0, r1, r2 in adj], axis=-1) / det[..., None]
