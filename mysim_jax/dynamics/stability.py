"""Explicit stability limits of fixed-step integrators on stiff springs.

Each spring-damper joining masses ``m_a`` and ``m_b`` (``1/m = 0`` for an anchor) is a
damped oscillator in its relative coordinate::

    ẍ = −ω² x − η ẋ,      ω² = k (1/m_a + 1/m_b),   η = c (1/m_a + 1/m_b)

The largest stable step of an integrator is the largest ``h`` for which its one-step
amplification matrix on this oscillator has spectral radius <= 1; it is found here by
bisection on that matrix, so it accounts for damping (which *lowers* the explicit limit:
for symplectic Euler ``h < 2(√(1+ζ²) − ζ)/ω`` with ``ζ = η / 2ω``).

The per-spring estimate ignores coupling: a mass between two springs raises the top
frequency (a uniform chain's top mode has ω² = 4k/m, not 2k/m). The config check therefore
uses :func:`network_stable_step`: the largest eigenvalue of the whole spring network's
mass-normalised stiffness ``M^-½ K M^-½`` (and of the damping matrix), with each spring
acting along its direction at the initial configuration, fed to the same one-oscillator
bisection. On the paper's rope net the per-spring estimate says 3.07e-4 s for
semi-implicit Euler, the network estimate 2.05e-4 s, and a run perturbed off the
symmetric plane (float64) blows up between 2.0e-4 and 2.1e-4 s
(``tests/test_config.py::test_network_stability_limit_brackets_the_measured_blow_up``;
runs that start exactly symmetric in float64 survive larger steps only because the
unstable antisymmetric modes are never excited).
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


# Exact eigenvalues up to this many degrees of freedom; beyond, a Gershgorin row-sum bound
# (an upper bound on the top eigenvalue, so the step it gives is conservative).
EXACT_EIG_MAX_DOF = 1500


def network_stable_step(integrator, node_a, node_b, stiffness, damping, inv_mass, direction):
    """Largest stable step of a network of spring-dampers, coupling included.

    ``node_a``, ``node_b`` ``(n_springs,)`` give each spring's ends as indices into
    ``inv_mass`` ``(n_dof_nodes,)`` (a node is a point mass or a rigid body, with its
    effective inverse mass), or ``-1`` for a fixed anchor. ``direction`` ``(n_springs, 3)``
    is each spring's unit direction (zero rows: a collapsed spring, counted in all
    directions). Returns ``(h_max, worst_spring)``: the step from the top eigenvalues of
    the mass-normalised stiffness and damping matrices, and the spring carrying the most
    strain energy in the top stiffness mode (to name in error messages).
    """
    if integrator in ("tsit5", "kvaerno5"):
        return math.inf, 0
    node_a = np.asarray(node_a, dtype=np.int64)
    node_b = np.asarray(node_b, dtype=np.int64)
    k = np.asarray(stiffness, dtype=float)
    c = np.asarray(damping, dtype=float)
    inv = np.asarray(inv_mass, dtype=float)
    u = np.asarray(direction, dtype=float).reshape(-1, 3)
    n = inv.shape[0]
    blocks = np.einsum("si,sj->sij", u, u)
    degenerate = np.abs(u).sum(axis=1) == 0.0
    blocks[degenerate] = np.eye(3)
    scale = np.sqrt(inv)

    def matrix(w):
        """Dense ``M^-½ (Σ w_s B_s) M^-½`` of size 3n (B_s the spring's 3x3 coupling)."""
        out = np.zeros((n, 3, n, 3))
        for s in range(k.shape[0]):
            a, b = node_a[s], node_b[s]
            blk = w[s] * blocks[s]
            if a >= 0:
                out[a, :, a, :] += blk * inv[a]
            if b >= 0:
                out[b, :, b, :] += blk * inv[b]
            if a >= 0 and b >= 0:
                off = blk * scale[a] * scale[b]
                out[a, :, b, :] -= off
                out[b, :, a, :] -= off
        return out.reshape(3 * n, 3 * n)

    def top(w):
        if n == 0:
            return 0.0, None
        if 3 * n <= EXACT_EIG_MAX_DOF:
            vals, vecs = np.linalg.eigh(matrix(w))
            return float(vals[-1]), vecs[:, -1].reshape(n, 3)
        # Gershgorin: row sums of |entries| without forming the matrix
        rows = np.zeros((n, 3))
        absb = np.abs(blocks).sum(axis=2) * w[:, None]          # (n_springs, 3)
        for s in range(k.shape[0]):
            a, b = node_a[s], node_b[s]
            for i, j in ((a, b), (b, a)):
                if i >= 0:
                    rows[i] += absb[s] * (inv[i] + (scale[i] * scale[j] if j >= 0 else 0.0))
        return float(rows.max()), None

    lam_k, mode = top(k)
    lam_c, _ = top(c)
    h = stable_step(integrator, math.sqrt(max(lam_k, 0.0)), max(lam_c, 0.0))
    worst = 0
    if mode is not None and k.shape[0]:
        disp = mode * scale[:, None]                             # physical displacements
        da = np.where(node_a[:, None] >= 0, disp[np.maximum(node_a, 0)], 0.0)
        db = np.where(node_b[:, None] >= 0, disp[np.maximum(node_b, 0)], 0.0)
        stretch = np.einsum("sij,sj->si", blocks, db - da)
        worst = int(np.argmax(k * np.einsum("si,si->s", db - da, stretch)))
    elif k.shape[0]:
        worst = int(np.argmax(k * (np.where(node_a >= 0, inv[np.maximum(node_a, 0)], 0.0)
                                   + np.where(node_b >= 0, inv[np.maximum(node_b, 0)], 0.0))))
    return h, worst
