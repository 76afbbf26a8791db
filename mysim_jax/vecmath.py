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
