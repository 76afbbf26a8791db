"""Explicit stability limits of fixed-step integrators on stiff springs.

Each spring-damper joining masses ``m_a`` and ``m_b`` (``1/m = 0`` for an anchor) is a
damped oscillator in its relative coordinate::

    ẍ = −ω² x − η ẋ,      ω² = k (1/m_a + 1/m_b),   η = c (1/m_a + 1/m_b)

The largest stable step of an integrator is the largest ``h`` for which its one-step
amplification matrix on this oscillator has spectral radius <= 1; it is found here by
bisection on that matrix, so it accounts for damping (which *lowers* the explicit limit:
for symplectic Euler ``h < 2(√(1+ζ²) − ζ)/ω`` with ``ζ = η / 2ω``).

This per-spring estimate is what the config check uses. It ignores coupling between
springs (a mass between two springs can raise the top frequency by up to √2), so it is a
necessary condition; on the paper's rope net it predicts 3.07e-4 s for semi-implicit Euler
and the measured blow-up lies between 3.0e-4 and 3.5e-4 s.
"""

from __future__ import annotations

import math

import numpy as np


def _amplification(integrator: str, h: float, omega: float, eta: float) -> np.ndarray:
    if integrator == "semi_implicit_euler":
        return np.array(
            [[1.0 - h * h * omega * omega, h * (1.0 - h * eta)], [-h * omega * omega, 1.0 - h * eta]]
        )
    if integrator == "rk4":
        a = np.array([[0.0, 1.0], [-omega * omega, -eta]]) * h
        out = np.eye(2)
        term = np.eye(2)
        for n in range(1, 5):
            term = term @ a / n
            out = out + term
        return out
    raise ValueError(f"no explicit stability limit for integrator {integrator!r}")


def stable_step(integrator: str, omega: float, eta: float) -> float:
    """Largest stable step for the oscillator ``ẍ = −ω²x − ηẋ`` (``inf`` if unconstrained)."""
    if integrator in ("tsit5", "kvaerno5"):
        return math.inf
    scale = max(omega, eta)
    if scale <= 0.0:
        return math.inf

    def stable(h):
        rho = np.max(np.abs(np.linalg.eigvals(_amplification(integrator, h, omega, eta))))
        return rho <= 1.0 + 1e-12

    lo, hi = 0.0, 10.0 / scale
    while stable(hi):      # very defensive: the regions used here are bounded
        hi *= 2.0
        if hi > 1e6 / scale:
            return math.inf
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if stable(mid):
            lo = mid
        else:
            hi = mid
    return lo


def spring_stable_steps(integrator, stiffness, damping, inv_mass_a, inv_mass_b) -> np.ndarray:
    """Per-spring stable step ``(n_springs,)`` from k, c and the inverse masses it joins."""
    inv = np.asarray(inv_mass_a, dtype=float) + np.asarray(inv_mass_b, dtype=float)
    omega = np.sqrt(np.asarray(stiffness, dtype=float) * inv)
    eta = np.asarray(damping, dtype=float) * inv
    return np.array([stable_step(integrator, w, e) for w, e in zip(omega, eta)])
