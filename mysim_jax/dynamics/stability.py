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
uses the whole network (:func:`scene_network_stable_step`), and it bounds the network over
*every configuration the ropes can take*, not only the initial one. Moving, stretched ropes
change the linearisation: a spring of stiffness k, tension T and length l has the tangent
stiffness ``k uuᵀ + (T/l)(I − uuᵀ)`` along its current direction u, and ropes that meet at
a mass at angles can swing into line. Since ``T/l = k (1 − l̄/l) <= k`` (negative for a
compressed linear spring) and ``c uuᵀ <= c I``, every spring's stiffness and damping are
below ``k I`` and ``c I`` in any configuration, so the top eigenvalues of the mass-normalised scalar weighted graph
Laplacians ``M^-½ L_k M^-½`` and ``M^-½ L_c M^-½`` (each spring counted in all three
directions) bound the network's top eigenvalues for good: ω²_max and η_max. The step is
the largest one stable for every oscillator with ω <= ω_max and η <= η_max
(:func:`stable_step_all_below`; for semi-implicit Euler the corner, for RK4 a smaller one
because its limit is not monotone in damping). A rigid body enters through the markers its
springs attach to (:func:`spring_network_nodes`).

The check accepts steps up to ``NETWORK_STEP_SAFETY`` (0.9) of that bound, for semi-implicit
Euler and RK4 alike. The figure is chosen from measurements (``scripts/stability_margin.py``
writes ``docs/stability.md``): float32 batches with random initial velocities up to 10 m/s
on every mass, on the rope net and on random networks built from the schema (stars and nets
of identical ropes, trees of unlike ones, bodies on markers, linear and tension-only). In
none of them does a spring network blow up at the bound itself, but where the bound is tight
(a stiff rope pulled straight) the first blow-ups come only a few percent above it; the
factor keeps every accepted step clear of the measured onsets and covers what the linear
bound leaves out (large-amplitude motion, the damping force's own geometric term
``c ṡ / l``, float32 round-off). RK4's onsets sit further above its bound, so the factor
costs it more than it needs; one figure keeps the rule simple. The trade: the bound is
configuration-independent, so on a scene whose ropes can never all line up (the paper's rope
net: four ropes from a payload to the corners of a square) it rejects steps that would in
fact run; docs/stability.md shows how far below the measured onset the accepted step sits.
``substeps: auto`` uses the same limit (no extra factor), so an auto step always passes.

Not a spring-network effect, and so not bounded here: a rigid body's gyroscopic term
``ω × Iω``. Taken explicitly, a fast-spinning body with unequal principal moments gains
energy every step, and ropes that jerk a body at an offset marker spin it up far enough
to blow up a net carried by bodies at accepted steps; semi-implicit Euler therefore takes
that term implicitly (:func:`mysim_jax.dynamics.integrators.implicit_gyroscopic`), and
docs/stability.md (``random_2`` against ``random_2:spherical``) shows the bodies' rotation
no longer sets the limit.
"""

from __future__ import annotations

import math

import numpy as np


# The config check accepts fixed steps up to this fraction of the spring network's bound
# (module docstring; chosen from docs/stability.md).
NETWORK_STEP_SAFETY = 0.9


# Integrators whose explicit parts step like another one: ``implicit_euler`` treats
# contact, Baumgarte terms and springs on body markers exactly as semi-implicit Euler does
# (its springs between point masses are implicit and are not checked here; see
# mysim_jax/build.py).
EXPLICIT_PART = {"implicit_euler": "semi_implicit_euler"}


def _amplification(integrator: str, h: float, omega: float, eta: float) -> np.ndarray:
    integrator = EXPLICIT_PART.get(integrator, integrator)
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


def _rk4_growth(z):
    """RK4's amplification factor ``R(z) = 1 + z + z²/2 + z³/6 + z⁴/24`` on ``ẏ = λy``, z = hλ."""
    return 1.0 + z * (1.0 + z * (0.5 + z * (1.0 / 6.0 + z / 24.0)))


def stable_step_all_below(integrator: str, omega_max: float, eta_max: float, n_samples: int = 512) -> float:
    """Largest step stable for *every* oscillator ``ẍ = −ω²x − ηẋ`` with ``ω <= omega_max``
    and ``η <= eta_max`` (the modes of a network whose stiffness and damping matrices have
    these top eigenvalues, when damping is not proportional to stiffness).

    Semi-implicit Euler's limit ``2 / (η/2 + √(ω² + η²/4))`` falls with both ω and η, so
    this is :func:`stable_step` at the corner. RK4's does not (damping can raise its limit,
    and a weakly stiff, strongly damped mode can be the worst): its amplification on a
    mode is ``R(hλ)`` at the mode's eigenvalues λ, which for all such oscillators fill
    ``{|λ| <= ω_max, Re λ >= −η_max/2, Re λ <= 0}`` plus the real segment ``[−η_max, 0]``
    (overdamped modes). ``R`` is a polynomial, so ``|R|`` is largest on that set's boundary
    (maximum modulus); the step is found by bisection on boundary samples.
    """
    if integrator != "rk4":
        return stable_step(integrator, omega_max, eta_max)
    if omega_max <= 0.0 and eta_max <= 0.0:
        return math.inf
    t = np.linspace(0.0, 1.0, n_samples)
    pts = [1j * omega_max * t, -eta_max * t]
    half = 0.5 * eta_max
    if omega_max > 0.0:
        top = math.pi / 2 + math.asin(min(1.0, half / omega_max))
        pts.append(omega_max * np.exp(1j * (math.pi / 2 + (top - math.pi / 2) * t)))
        if half < omega_max:
            pts.append(-half + 1j * math.sqrt(omega_max ** 2 - half ** 2) * t)
    pts = np.concatenate(pts)
    lo, hi = 0.0, 10.0 / max(omega_max, eta_max)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if np.abs(_rk4_growth(mid * pts)).max() <= 1.0 + 1e-12:
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


# Exact eigenvalues up to this many nodes; beyond, a Gershgorin row-sum bound (an upper
# bound on the top eigenvalue, so the step it gives is conservative).
EXACT_EIG_MAX_NODES = 1500


def _laplacian_top(node_a, node_b, weight, inv_mass):
    """Top eigenvalue and eigenvector of the mass-normalised weighted graph Laplacian
    ``M^-½ L M^-½`` (``L = Σ_s w_s (e_a − e_b)(e_a − e_b)ᵀ``, anchors dropped).
    The vector is ``None`` above :data:`EXACT_EIG_MAX_NODES` (Gershgorin bound)."""
    n = inv_mass.shape[0]
    if n == 0 or weight.shape[0] == 0:
        return 0.0, None
    scale = np.sqrt(inv_mass)
    a_ok, b_ok = node_a >= 0, node_b >= 0
    a, b = np.maximum(node_a, 0), np.maximum(node_b, 0)
    if n <= EXACT_EIG_MAX_NODES:
        lap = np.zeros((n, n))
        np.add.at(lap, (a[a_ok], a[a_ok]), weight[a_ok])
        np.add.at(lap, (b[b_ok], b[b_ok]), weight[b_ok])
        both = a_ok & b_ok
        np.add.at(lap, (a[both], b[both]), -weight[both])
        np.add.at(lap, (b[both], a[both]), -weight[both])
        vals, vecs = np.linalg.eigh(scale[:, None] * lap * scale[None, :])
        return float(vals[-1]), vecs[:, -1]
    rows = np.zeros(n)
    both = a_ok & b_ok
    np.add.at(rows, a[a_ok], weight[a_ok] * inv_mass[a[a_ok]])
    np.add.at(rows, b[b_ok], weight[b_ok] * inv_mass[b[b_ok]])
    np.add.at(rows, a[both], weight[both] * scale[a[both]] * scale[b[both]])
    np.add.at(rows, b[both], weight[both] * scale[a[both]] * scale[b[both]])
    return float(rows.max()), None


def _directional_top(node_a, node_b, weight, inv_mass, direction):
    """Top eigenvalue of ``M^-½ (Σ_s w_s (e_a − e_b)(e_a − e_b)ᵀ ⊗ u_s u_sᵀ) M^-½`` (3n x 3n):
    each spring acting only along ``u_s`` (a zero row: in all directions)."""
    n = inv_mass.shape[0]
    if n == 0 or weight.shape[0] == 0:
        return 0.0
    blocks = np.einsum("si,sj->sij", direction, direction)
    blocks[np.abs(direction).sum(axis=1) == 0.0] = np.eye(3)
    scale = np.sqrt(inv_mass)
    out = np.zeros((n, 3, n, 3))
    for s in range(weight.shape[0]):
        a, b = node_a[s], node_b[s]
        blk = weight[s] * blocks[s]
        if a >= 0:
            out[a, :, a, :] += blk * inv_mass[a]
        if b >= 0:
            out[b, :, b, :] += blk * inv_mass[b]
        if a >= 0 and b >= 0:
            out[a, :, b, :] -= blk * scale[a] * scale[b]
            out[b, :, a, :] -= blk * scale[a] * scale[b]
    return float(np.linalg.eigvalsh(out.reshape(3 * n, 3 * n))[-1])


def network_stable_step(integrator, node_a, node_b, stiffness, damping, inv_mass, direction=None):
    """Largest stable step of a network of spring-dampers, coupling included.

    ``node_a``, ``node_b`` ``(n_springs,)`` give each spring's ends as indices into
    ``inv_mass`` ``(n_nodes,)`` (the inverse mass of each 3-DOF node), or ``-1`` for a
    fixed end. With ``direction=None`` (what the config check uses) every spring counts
    in all three directions: the scalar weighted graph Laplacian, whose top eigenvalue
    bounds the network's for every configuration (module docstring). With ``direction``
    ``(n_springs, 3)`` (unit rows) each spring acts only along its row: the linearisation
    at that one configuration, kept to compare against (``scripts/stability_margin.py``).

    Returns ``(h_max, worst_spring)``: the step from the top eigenvalues of the
    mass-normalised stiffness and damping matrices, and the spring carrying the most
    strain energy in the top stiffness mode (to name in error messages).
    """
    if integrator in ("tsit5", "kvaerno5"):
        return math.inf, 0
    node_a = np.asarray(node_a, dtype=np.int64).reshape(-1)
    node_b = np.asarray(node_b, dtype=np.int64).reshape(-1)
    k = np.asarray(stiffness, dtype=float).reshape(-1)
    c = np.asarray(damping, dtype=float).reshape(-1)
    inv = np.asarray(inv_mass, dtype=float).reshape(-1)
    lam_k, mode = _laplacian_top(node_a, node_b, k, inv)
    lam_c, _ = _laplacian_top(node_a, node_b, c, inv)
    if direction is not None:
        u = np.asarray(direction, dtype=float).reshape(-1, 3)
        lam_k = _directional_top(node_a, node_b, k, inv, u)
        lam_c = _directional_top(node_a, node_b, c, inv, u)
    h = stable_step_all_below(integrator, math.sqrt(max(lam_k, 0.0)), max(lam_c, 0.0))
    worst = 0
    if k.shape[0]:
        if mode is not None:
            disp = mode * np.sqrt(inv)                  # physical displacements of the top mode
            da = np.where(node_a >= 0, disp[np.maximum(node_a, 0)], 0.0)
            db = np.where(node_b >= 0, disp[np.maximum(node_b, 0)], 0.0)
            worst = int(np.argmax(k * (db - da) ** 2))
        else:
            ends = (np.where(node_a >= 0, inv[np.maximum(node_a, 0)], 0.0)
                    + np.where(node_b >= 0, inv[np.maximum(node_b, 0)], 0.0))
            worst = int(np.argmax(k * ends))
    return h, worst


def spring_network_nodes(n_points, marker_body, node_a, node_b, point_mass, body_mass, inertia, marker_pos):
    """Map a scene's springs onto 3-DOF nodes for :func:`network_stable_step`.

    Scene nodes (``[0, n_points)`` points, then markers, then anchors) become: each point
    mass its own node; each marker that carries a spring its own node; anchors ``-1``.
    A body whose springs attach at ``n_b`` markers gives each of them the inverse mass
    ``n_b (1/m + |r_i|²/I_min)`` (``r_i`` the marker's offset): a motion of the body with
    kinetic energy E moves marker i by at most ``√(2E (1/m + |r_i|²/I_min))``, so these
    masses never carry more kinetic energy than the body does, and the network's top
    eigenvalue is bounded whatever the body's attitude and however its markers move
    relative to each other. (Treating the body as one node shared by all its markers would
    miss its rotation modes.) Springs with both ends on one body exert no net force or
    torque on it and are left out.

    Returns ``(dof_a, dof_b, inv_mass, kept)``: node indices per kept spring, the inverse
    masses, and the indices of the kept springs.
    """
    marker_body = np.asarray(marker_body, dtype=np.int64).reshape(-1)
    n_markers = marker_body.shape[0]
    node_a = np.asarray(node_a, dtype=np.int64).reshape(-1)
    node_b = np.asarray(node_b, dtype=np.int64).reshape(-1)
    marker_pos = np.asarray(marker_pos, dtype=float).reshape(-1, 3)
    inertia = np.asarray(inertia, dtype=float).reshape(-1, 3, 3)
    body_mass = np.asarray(body_mass, dtype=float).reshape(-1)

    def body_of(node):
        return int(marker_body[node - n_points]) if n_points <= node < n_points + n_markers else -1

    def fixed(node):
        return node >= n_points + n_markers

    kept = np.array([s for s in range(node_a.shape[0])
                     if not (fixed(node_a[s]) and fixed(node_b[s]))
                     and not (body_of(node_a[s]) >= 0 and body_of(node_a[s]) == body_of(node_b[s]))],
                    dtype=np.int64)
    used = sorted({int(x) - n_points for x in np.concatenate([node_a[kept], node_b[kept]])
                   if n_points <= x < n_points + n_markers})
    per_body = np.bincount(marker_body[used], minlength=body_mass.shape[0]) if used else np.zeros(0, int)
    i_min = np.array([np.linalg.eigvalsh(i).min() for i in inertia]) if inertia.shape[0] else np.zeros(0)
    inv_mass = list(1.0 / np.asarray(point_mass, dtype=float).reshape(-1))
    marker_dof = {}
    for m in used:
        b = marker_body[m]
        marker_dof[m] = len(inv_mass)
        inv_mass.append(per_body[b] * (1.0 / body_mass[b] + float(marker_pos[m] @ marker_pos[m]) / i_min[b]))

    def dof(node):
        if node < n_points:
            return int(node)
        if node < n_points + n_markers:
            return marker_dof[int(node) - n_points]
        return -1

    return (np.array([dof(x) for x in node_a[kept]], dtype=np.int64),
            np.array([dof(x) for x in node_b[kept]], dtype=np.int64),
            np.asarray(inv_mass, dtype=float), kept)


def scene_network_stable_step(integrator, scene, point_mass, body_mass, inertia, marker_pos,
                              stiffness, damping, node_pos=None):
    """The bound :func:`network_stable_step` of a scene's whole spring network.

    ``scene`` supplies the topology (``n_points``, ``marker_body``, ``spring_node_a/b``);
    the arrays are host-side NumPy (masses ``(n_points,)``, ``(n_bodies,)``, inertias
    ``(n_bodies, 3, 3)`` body frame, marker offsets ``(n_markers, 3)``, spring constants
    ``(n_springs,)``). With ``node_pos`` ``(n_nodes, 3)`` (world positions of all nodes)
    the springs act along their directions there instead (for comparison only).
    Returns ``(h, worst)``, ``worst`` an index into the scene's springs (0 without any).
    """
    if not len(scene.spring_node_a):
        return math.inf, 0
    dof_a, dof_b, inv_mass, kept = spring_network_nodes(
        scene.n_points, scene.marker_body, scene.spring_node_a, scene.spring_node_b,
        point_mass, body_mass, inertia, marker_pos)
    if kept.shape[0] == 0:
        return math.inf, 0
    direction = None
    if node_pos is not None:
        node_pos = np.asarray(node_pos, dtype=float)
        d = (node_pos[np.asarray(scene.spring_node_b)[kept]] - node_pos[np.asarray(scene.spring_node_a)[kept]])
        length = np.linalg.norm(d, axis=1, keepdims=True)
        direction = np.where(length > 0, d / np.where(length > 0, length, 1.0), 0.0)
    h, worst = network_stable_step(integrator, dof_a, dof_b, np.asarray(stiffness, float)[kept],
                                   np.asarray(damping, float)[kept], inv_mass, direction)
    return h, int(kept[worst])
