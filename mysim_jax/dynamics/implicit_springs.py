"""Linearly implicit (Baraff–Witkin) velocity update of point masses on stiff springs.

Used by :class:`mysim_jax.dynamics.integrators.ImplicitEuler`. One step of backward Euler
on the point masses, linearised once about the current state (Baraff & Witkin, SIGGRAPH
1998), asks for the velocity change ``Δv`` of all points at once::

    (M + h D + h² S) Δv = h (f(x, v) − h S v),        then  v' = v + Δv,  x' = x + h v'

``f`` is the total force on the points (every force stage, gravity included), ``S`` and
``D`` the stiffness and damping matrices of the *implicit springs*: rope segments and
springs whose ends are both point masses, or a point mass and a fixed anchor. (In the
sign convention ``K = ∂f/∂x = −S`` and ``C = ∂f/∂v = −D`` this is
``(M − hC − h²K) Δv = h (f + h K v)``.) Springs with an end on a rigid-body marker are
not in ``S`` and ``D``: their force enters ``f`` explicitly, as do contact, rotors, drag,
loads and everything that acts on bodies. Why only these: the stiff, numerous elements of a
net are the springs between its lumped masses, and their Jacobian is a sparse 3 x 3-block
graph Laplacian that a few gathers and one ``segment_sum`` apply; a marker's end moves with
a body whose rotation and joint constraints would couple the solve to the Newton–Euler
equations and the constraint solve.

Each implicit spring with unit direction ``u``, stiffness ``k``, damping ``c``, length
``l`` and rest length ``l̄`` contributes the 3 x 3 blocks

    S_s = k uuᵀ + g (I − uuᵀ),   g = k max(l − l̄, 0) / l   (0 <= g < k),    D_s = c uuᵀ

to the rows of its two ends (``+`` on the diagonal blocks, ``−`` off them), which makes
``S`` and ``D`` positive semi-definite and the system matrix symmetric positive definite:

* the geometric (transverse) stiffness ``g`` comes from the elastic tension only, and
  only when it pulls: a compressed linear spring's negative geometric stiffness (which
  could make the matrix indefinite) is dropped, as is the damping force's own geometric
  term ``c ṡ (I − uuᵀ)/l`` and the non-symmetric part of ``∂(c ṡ u)/∂x``;
* a ``tension_only`` segment that does not pull (slack, or taut with the damper cancelling
  the spring) exerts no force and has no stiffness or damping (``S_s = D_s = 0``).

These approximations change only the matrix, not the force ``f`` on the right-hand side,
so the step stays a consistent first-order method (it reduces to semi-implicit Euler as
``h → 0``); they only weaken the damping of the highest modes that an exact Jacobian
would give.

The system is solved matrix-free by preconditioned conjugate gradients with a fixed number
of iterations (``sim.implicit_iterations``, a static parameter: a ``fori_loop`` of fixed
length, so the solve is differentiable in reverse mode and vmappable). The matrix is never
formed: ``A x`` is a gather of the springs' end values, the blocks above applied to the
difference, and a ``segment_sum`` back onto the points. The preconditioner is block Jacobi
(the 3 x 3 diagonal block of every point, inverted in closed form). CG starts from the
explicit update ``Δv₀ = h a`` (``a = f/M``), so with zero iterations the step *is*
semi-implicit Euler, and at small steps the initial residual is already ``O(h²)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.dynamics.markers import take_rows
from mysim_jax.core.types import Params, PhysState, Scene

@dataclass(frozen=True)
class ImplicitSprings:
    """Which of a scene's springs are taken implicitly, and their ends (static).

    Ends are indices into the table ``[points; anchors]`` (``n_points + j`` for anchor
    ``j``); anchors neither move nor take a velocity change.
    """

    spring: tuple[int, ...]         # (n_implicit,) indices into the scene's springs
    end_a: tuple[int, ...]          # (n_implicit,) point index, or n_points + anchor index
    end_b: tuple[int, ...]          # (n_implicit,)
    tension_only: tuple[bool, ...]  # (n_implicit,)
    n_points: int
    n_anchors: int

    @property
    def n_springs(self) -> int:
        return len(self.spring)


def spring_ends_on_markers(scene: Scene) -> np.ndarray:
    """Indices ``(k,)`` of the scene's springs with an end on a rigid-body marker (these stay
    explicit in :class:`~mysim_jax.dynamics.integrators.ImplicitEuler`)."""
    a = np.asarray(scene.spring_node_a, dtype=np.int64)
    b = np.asarray(scene.spring_node_b, dtype=np.int64)
    lo, hi = scene.n_points, scene.n_points + scene.n_markers

    def on_marker(n):
        return (n >= lo) & (n < hi)

    return np.flatnonzero(on_marker(a) | on_marker(b))


@functools.lru_cache(maxsize=64)
def implicit_springs(scene: Scene) -> ImplicitSprings:
    """The springs of ``scene`` joining two point masses or a point mass and an anchor."""
    a = np.asarray(scene.spring_node_a, dtype=np.int64)
    b = np.asarray(scene.spring_node_b, dtype=np.int64)
    n_p, n_m = scene.n_points, scene.n_markers
    on_point = lambda n: n < n_p                  # noqa: E731
    on_anchor = lambda n: n >= n_p + n_m          # noqa: E731
    keep = ((on_point(a) | on_anchor(a)) & (on_point(b) | on_anchor(b)) & (on_point(a) | on_point(b)))
    idx = np.flatnonzero(keep)

    def end(n):
        return n if n < n_p else n - n_m          # anchors follow the points in [points; anchors]

    return ImplicitSprings(
        spring=tuple(int(s) for s in idx),
        end_a=tuple(int(end(n)) for n in a[idx]),
        end_b=tuple(int(end(n)) for n in b[idx]),
        tension_only=tuple(bool(scene.spring_tension_only[s]) for s in idx),
        n_points=n_p,
        n_anchors=scene.n_anchors,
    )


@struct.dataclass
class SpringLinearisation:
    """The implicit springs' PSD stiffness and damping at one state (module docstring)."""

    unit: jnp.ndarray        # (n_implicit, 3) direction from end a to end b
    axial: jnp.ndarray       # (n_implicit,) N/m, stiffness along u (k, or 0 when not pulling)
    transverse: jnp.ndarray  # (n_implicit,) N/m, geometric stiffness across u (0 <= g < k)
    damping: jnp.ndarray     # (n_implicit,) N s/m, along u


def linearise(springs: ImplicitSprings, params: Params, point_pos, point_vel) -> SpringLinearisation:
    """Stiffness and damping of the implicit springs at positions and velocities
    ``(n_points, 3)`` (module docstring for the PSD approximation)."""
    s = np.asarray(springs.spring, dtype=np.int32)
    ends_a = np.asarray(springs.end_a, dtype=np.int32)
    ends_b = np.asarray(springs.end_b, dtype=np.int32)
    pos = jnp.concatenate([point_pos, params.anchor_pos], axis=0)
    vel = jnp.concatenate([point_vel, jnp.zeros_like(params.anchor_pos)], axis=0)
    dx = take_rows(pos, ends_b) - take_rows(pos, ends_a)
    dv = take_rows(vel, ends_b) - take_rows(vel, ends_a)
    length, unit = vecmath.safe_unit(dx)
    k = params.spring_stiffness[s]
    c = params.spring_damping[s]
    rest = params.spring_rest_length[s]
    rate = vecmath.dot(dv, unit)
    tension_only = np.asarray(springs.tension_only, dtype=bool)
    if tension_only.any():
        tension = spring_tension(k, c, rest, length, rate, tension_only)
        pulling = jnp.where(tension_only, tension > 0.0, True)
        k = jnp.where(pulling, k, 0.0)
        c = jnp.where(pulling, c, 0.0)
    stretched = length > rest
    safe_length = jnp.where(stretched, length, 1.0)
    transverse = jnp.where(stretched, k * (length - rest) / safe_length, 0.0)
    return SpringLinearisation(unit=unit, axial=k, transverse=transverse, damping=c)


def network_product(springs: ImplicitSprings, unit, axial, transverse, x):
    """``L x`` ``(n_points, 3)`` for the block graph Laplacian ``L = Σ_s (e_a − e_b)(e_a − e_b)ᵀ
    ⊗ (axial_s uuᵀ + transverse_s (I − uuᵀ))`` of the implicit springs; ``x`` ``(n_points, 3)``
    (anchors hold zero)."""
    n_p = springs.n_points
    ends_a = np.asarray(springs.end_a, dtype=np.int32)
    ends_b = np.asarray(springs.end_b, dtype=np.int32)
    if springs.n_anchors:
        x = jnp.concatenate([x, jnp.zeros((springs.n_anchors, 3), x.dtype)], axis=0)
    rel = take_rows(x, ends_b) - take_rows(x, ends_a)
    along = vecmath.dot(unit, rel)
    y = (axial - transverse)[:, None] * along[:, None] * unit + transverse[:, None] * rel
    n = n_p + springs.n_anchors
    out = jax.ops.segment_sum(y, ends_b, num_segments=n) - jax.ops.segment_sum(y, ends_a, num_segments=n)
    return out[:n_p]


def _block_diagonal(springs: ImplicitSprings, unit, axial, transverse, mass):
    """The 3 x 3 diagonal blocks ``(n_points, 3, 3)`` of ``diag(mass) ⊗ I + L``."""
    n = springs.n_points + springs.n_anchors
    uu = unit[:, :, None] * unit[:, None, :]
    eye = jnp.eye(3, dtype=unit.dtype)
    blocks = (axial - transverse)[:, None, None] * uu + transverse[:, None, None] * eye
    ends_a = np.asarray(springs.end_a, dtype=np.int32)
    ends_b = np.asarray(springs.end_b, dtype=np.int32)
    summed = (jax.ops.segment_sum(blocks, ends_a, num_segments=n)
              + jax.ops.segment_sum(blocks, ends_b, num_segments=n))[:springs.n_points]
    return summed + mass[:, None, None] * eye


@struct.dataclass
class VelocitySystem:
    """``A Δv = b`` of one linearised backward-Euler step (module docstring)."""

    lin: SpringLinearisation
    mass: jnp.ndarray   # (n_points,)
    h: jnp.ndarray      # ()
    rhs: jnp.ndarray    # (n_points, 3)

    def matvec(self, springs: ImplicitSprings, x):
        """``A x = M x + L_{hD + h²S} x``."""
        h = self.h
        axial = h * self.lin.damping + h * h * self.lin.axial
        return self.mass[:, None] * x + network_product(springs, self.lin.unit, axial, h * h * self.lin.transverse,
                                                          x)

    def block_diagonal(self, springs: ImplicitSprings):
        h = self.h
        axial = h * self.lin.damping + h * h * self.lin.axial
        return _block_diagonal(springs, self.lin.unit, axial, h * h * self.lin.transverse, self.mass)


def velocity_system(springs: ImplicitSprings, params: Params, phys: PhysState, point_acc, h) -> VelocitySystem:
    """The linear system for ``Δv`` at state ``phys``, with ``point_acc`` ``(n_points, 3)``
    the total acceleration of every point there (all forces, explicit and implicit)."""
    lin = linearise(springs, params, phys.point_pos, phys.point_vel)
    mass = params.point_mass
    stiff_v = network_product(springs, lin.unit, lin.axial, lin.transverse, phys.point_vel)
    rhs = h * (mass[:, None] * point_acc - h * stiff_v)
    return VelocitySystem(lin=lin, mass=mass, h=h, rhs=rhs)


def _safe_ratio(num, den):
    """``num / den``, and 0 where ``den`` is 0 (a converged CG), with finite gradients."""
    ok = den > 0.0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def conjugate_gradient(matvec, rhs, x0, iterations: int, precondition=None):
    """``iterations`` steps of (preconditioned) conjugate gradients on ``A x = rhs`` from
    ``x0``; ``A`` symmetric positive definite, given by ``matvec``. A fixed number of steps
    (a ``fori_loop`` of static length), so reverse-mode differentiable; once the residual
    is exactly zero further steps change nothing."""
    if precondition is None:
        precondition = lambda r: r                # noqa: E731

    def body(_, carry):
        x, r, p, rz = carry
        ap = matvec(p)
        alpha = _safe_ratio(rz, jnp.sum(p * ap))
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        rz_new = jnp.sum(r * z)
        p = z + _safe_ratio(rz_new, rz) * p
        return x, r, p, rz_new

    r = rhs - matvec(x0)
    z = precondition(r)
    x, *_ = jax.lax.fori_loop(0, iterations, body, (x0, r, z, jnp.sum(r * z)))
    return x


def solve_velocity_change(springs: ImplicitSprings, system: VelocitySystem, x0, iterations: int):
    """``Δv`` ``(n_points, 3)`` from ``iterations`` block-Jacobi-preconditioned CG steps."""
    inverse = vecmath.inv3(system.block_diagonal(springs))

    def precondition(r):
        return jnp.einsum("nij,nj->ni", inverse, r)

    return conjugate_gradient(lambda x: system.matvec(springs, x), system.rhs, x0, iterations, precondition)


@dataclass(frozen=True)
class ImplicitSpringSolve:
    """The implicit part handed to :class:`~mysim_jax.dynamics.integrators.ImplicitEuler`
    by :func:`mysim_jax.sim.step`: maps (state, total point accelerations, step) to the
    points' velocity change."""

    scene: Scene
    params: Params
    iterations: int

    def velocity_change(self, phys: PhysState, point_acc, h):
        springs = implicit_springs(self.scene)
        if springs.n_springs == 0 or self.iterations == 0:
            return h * point_acc
        system = velocity_system(springs, self.params, phys, point_acc, h)
        return solve_velocity_change(springs, system, h * point_acc, self.iterations)
