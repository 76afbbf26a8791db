"""The team's target track: a constant-acceleration Kalman filter on the fused target positions.

The fused localisation (:mod:`mysim_jax.perception.localize`) gives the target's position
at every camera frame it is seen in; the capture team also needs its velocity. This filter
estimates position, velocity and acceleration, per axis independently, from the positions
alone (NaN rows: no fix that frame, the filter predicts through them). The acceleration is
a state, so a falling target (constant g) is followed without lag. Model, per axis with
state ``(p, v, a)`` (the discrete Wiener-process-acceleration model)::

    p' = p + v Δt + ½ a Δt² + ⅙ j Δt³,  v' = v + a Δt + ½ j Δt²,  a' = a + j Δt,
    j ~ N(0, jerk_sigma²) per step;     z = p + n,  n ~ N(0, position_sigma²)

The first fix starts it at rest, with standard deviations ``initial_speed_sigma`` and
``initial_accel_sigma`` on velocity and acceleration. NumPy only.
"""

from __future__ import annotations

import numpy as np


def target_filter(t, positions, position_sigma: float = 0.05, jerk_sigma: float = 5.0,
                  initial_speed_sigma: float = 5.0, initial_accel_sigma: float = 10.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Filtered positions and velocities ``(F, 3)`` (m, m/s; NaN before the first fix).

    ``t`` ``(F,)`` s increasing; ``positions`` ``(F, 3)`` m, NaN rows where there is no fix;
    ``position_sigma`` m, the fixes' noise; ``jerk_sigma`` m/s³, how quickly the target's
    acceleration may change (a falling target: small; an evading drone: large)."""
    t = np.asarray(t, dtype=float)
    z = np.asarray(positions, dtype=float)
    if t.ndim != 1 or z.shape != (len(t), 3):
        raise ValueError(f"target_filter: t (F,) and positions (F, 3), got {t.shape} and {z.shape}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("target_filter: t must increase")
    if min(position_sigma, jerk_sigma, initial_speed_sigma, initial_accel_sigma) <= 0:
        raise ValueError("target_filter: the sigmas must be positive")
    n = len(t)
    p_out, v_out = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    x = None                                   # (3, 3): rows p, v, a; one column per axis
    P = None                                   # (3, 3): the same covariance on every axis
    r = position_sigma ** 2
    for k in range(n):
        fix = np.all(np.isfinite(z[k]))
        if x is None:
            if not fix:
                continue
            x = np.stack([z[k], np.zeros(3), np.zeros(3)])
            P = np.diag([r, initial_speed_sigma ** 2, initial_accel_sigma ** 2])
        else:
            dt = t[k] - t[k - 1]
            F = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            G = np.array([[dt ** 3 / 6], [dt * dt / 2], [dt]])
            x = F @ x
            P = F @ P @ F.T + jerk_sigma ** 2 * (G @ G.T)
            if fix:
                gain = P[:, :1] / (P[0, 0] + r)                  # (3, 1)
                x = x + gain @ (z[k] - x[0])[None, :]
                P = P - gain @ P[:1, :]
        p_out[k], v_out[k] = x[0], x[1]
    return p_out, v_out
