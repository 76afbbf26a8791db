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
