"""Time integrators for the multibody state.

All integrators share one small interface: ``step(accel_fn, phys, h) -> phys`` advances
a :class:`~mysim_jax.core.types.PhysState` by ``h`` given ``accel_fn(phys) -> Accelerations``.
They hold no memory between steps.

* :class:`SemiImplicitEuler` — symplectic Euler: velocities first, then positions with
  the new velocities; attitude by the exact exponential map ``q ⊗ exp(½ ω h)``. The
  gyroscopic term of Euler's equations is taken implicitly (:func:`implicit_gyroscopic`):
  explicit in it, a body spinning about an axis of unequal moments gains energy every
  step and, tied to stiff ropes, blows up at steps the spring network allows.
  First order, cheap, energy-stable; the default for RL-scale batches.
* :class:`RK4` — classical 4th-order Runge-Kutta on (positions, quaternions, velocities)
  with ``dq/dt = ½ q ⊗ ω``; quaternions renormalised after each step.
* :class:`ImplicitEuler` — semi-implicit Euler whose point-mass velocity update is one
  linearised backward-Euler solve on the springs between point masses (and to anchors):
  stable far above the explicit limit of a stiff rope network. First order.

Adaptive diffrax solvers (``tsit5`` explicit, ``kvaerno5`` implicit for stiff problems)
are driven from :mod:`mysim_jax.sim` since they integrate over an interval, not one step.
"""

from __future__ import annotations

import abc
from typing import Callable

import jax
import jax.numpy as jnp

from mysim_jax.core import vecmath
from mysim_jax.dynamics.quaternion import quat_derivative, quat_integrate, quat_normalize
from mysim_jax.core.types import Accelerations, PhysState

AccelFn = Callable[[PhysState], Accelerations]


class Integrator(abc.ABC):
    """Advance a multibody state by one fixed step.

    ``step(accel_fn, phys, h, body_inertia, implicit)`` must be pure: no state is kept on
    the integrator. ``body_inertia`` ``(n_bodies, 3, 3)`` (body frame) is for integrators
    that treat part of Euler's equations implicitly; others ignore it. ``implicit`` is
    given only to integrators with ``takes_implicit_springs``: an object whose
    ``velocity_change(phys, point_acc, h)`` returns the points' velocity change of a
    linearised backward-Euler step on the springs between point masses
    (:class:`~mysim_jax.dynamics.implicit_springs.ImplicitSpringSolve`).
    """

    takes_implicit_springs: bool = False

    @abc.abstractmethod
    def step(self, accel_fn: AccelFn, phys: PhysState, h, body_inertia=None, implicit=None) -> PhysState:
        ...


def implicit_gyroscopic(inertia, omega, angacc, h):
    """Angular acceleration ``(n, 3)`` that advances ``ω`` by one Newton step of backward
    Euler on the gyroscopic term.

    ``angacc = J⁻¹(τ − ω × Jω)`` is the explicit acceleration (with any constraint
    correction). Backward Euler asks for ``J (ω' − ω) + h (ω' × Jω' − τ) = 0``; one Newton
    step from ``ω`` gives ``ω' = ω + h (J + h (ω̂ J − (Jω)^))⁻¹ J angacc`` (ω̂ the cross-product
    matrix), the update of Catto (GDC 2015) and Bullet's implicit gyroscopic forces. It
    equals the explicit one to first order in ``h``, does not feed energy into a free
    spin, and leaves a body without spin (``ω = 0``) exactly as before.
    """
    j_omega = jnp.einsum("nij,nj->ni", inertia, omega)
    jacobian = inertia + h * (jnp.einsum("nij,njk->nik", vecmath.skew(omega), inertia) - vecmath.skew(j_omega))
    return vecmath.solve3(jacobian, jnp.einsum("nij,nj->ni", inertia, angacc))


def state_derivative(phys: PhysState, acc: Accelerations) -> PhysState:
    """Time derivative of a state, in the same pytree shape (quaternion rate ½ q ⊗ ω)."""
    return PhysState(
        point_pos=phys.point_vel,
        point_vel=acc.point_acc,
        body_pos=phys.body_vel,
        body_quat=quat_derivative(phys.body_quat, phys.body_angvel),
        body_vel=acc.body_acc,
        body_angvel=acc.body_angacc,
    )


def symplectic_update(phys: PhysState, acc: Accelerations, point_vel, h, body_inertia=None) -> PhysState:
    """The rest of a semi-implicit Euler step once the points' new velocities ``point_vel``
    ``(n_points, 3)`` are known: points move with them, bodies update their velocities
    from ``acc`` (the gyroscopic term implicitly) and then move with the new ones."""
    body_vel = phys.body_vel + h * acc.body_acc
    angacc = acc.body_angacc
    if body_inertia is not None and body_inertia.shape[0]:
        angacc = implicit_gyroscopic(body_inertia, phys.body_angvel, angacc, h)
    body_angvel = phys.body_angvel + h * angacc
    return PhysState(
        point_pos=phys.point_pos + h * point_vel,
        point_vel=point_vel,
        body_pos=phys.body_pos + h * body_vel,
        body_quat=quat_integrate(phys.body_quat, body_angvel, h),
        body_vel=body_vel,
        body_angvel=body_angvel,
    )


class SemiImplicitEuler(Integrator):
    """Symplectic (semi-implicit) Euler."""

    def step(self, accel_fn, phys, h, body_inertia=None, implicit=None):
        acc = accel_fn(phys)
        return symplectic_update(phys, acc, phys.point_vel + h * acc.point_acc, h, body_inertia)


class RK4(Integrator):
    """Classical fourth-order Runge-Kutta.

    The four stages run as a ``lax.scan`` over the Butcher coefficients, so the force
    pipeline is traced (and compiled) once instead of four times, which shortens the
    compile of a jointed scene.
    """

    _A = (0.0, 0.5, 0.5, 1.0)          # stage offsets c_i = a_i,i-1
    _W = (1.0 / 6, 2.0 / 6, 2.0 / 6, 1.0 / 6)

    def step(self, accel_fn, phys, h, body_inertia=None, implicit=None):
        def f(y):
            return state_derivative(y, accel_fn(y))

        dtype = phys.point_pos.dtype
        coeffs = (jnp.asarray(self._A, dtype), jnp.asarray(self._W, dtype))

        def stage(carry, coef):
            k_prev, k_sum = carry
            a, w = coef
            k = f(jax.tree.map(lambda y, kp: y + (a * h) * kp, phys, k_prev))
            return (k, jax.tree.map(lambda s, kk: s + w * kk, k_sum, k)), None

        zeros = jax.tree.map(jnp.zeros_like, phys)
        (_, k_sum), _ = jax.lax.scan(stage, (zeros, zeros), coeffs)
        out = jax.tree.map(lambda y, k: y + h * k, phys, k_sum)
        return out.replace(body_quat=quat_normalize(out.body_quat))


class ImplicitEuler(Integrator):
    """Semi-implicit Euler with the springs between point masses taken implicitly.

    Implicit: the velocity update of the point masses, ``(M + hD + h²S) Δv = h (f − h S v)``
    (one Newton step of backward Euler, linearised at the current state), where ``S`` and
    ``D`` are the positive semi-definite stiffness and damping of the rope segments and
    springs joining two point masses or a point mass and an anchor
    (:mod:`mysim_jax.dynamics.implicit_springs`); solved by a fixed number of
    block-Jacobi-preconditioned conjugate-gradient iterations (``sim.implicit_iterations``).
    Then ``x' = x + h v'``.

    Explicit, exactly as in :class:`SemiImplicitEuler`: every force in ``f`` is evaluated
    at the current state (contact, rotors, drag, loads, gravity, and springs with an end
    on a body marker), rigid bodies (velocity update, the implicit gyroscopic term,
    attitude by the exponential map) and joint constraints. Those keep their explicit
    step limits, which the builder's check still applies; the spring network between
    point masses does not limit the step.

    Why this split: a net's stiffness sits in its many short segments between light lumped
    masses; their Jacobian is a sparse, symmetric graph Laplacian of 3 x 3 blocks that a
    few gathers and ``segment_sum`` apply without forming a matrix, so the solve stays
    vmappable and differentiable. Taking body-attached springs, contact or joints
    implicitly would couple the solve to rotations, constraint forces and non-smooth
    contact laws.

    First order (backward Euler damps the fastest modes strongly: the price of its
    stability); with zero CG iterations it is exactly semi-implicit Euler.
    """

    takes_implicit_springs = True

    def step(self, accel_fn, phys, h, body_inertia=None, implicit=None):
        acc = accel_fn(phys)
        dv = h * acc.point_acc if implicit is None else implicit.velocity_change(phys, acc.point_acc, h)
        return symplectic_update(phys, acc, phys.point_vel + dv, h, body_inertia)


FIXED_STEP = {"semi_implicit_euler": SemiImplicitEuler(), "rk4": RK4(), "implicit_euler": ImplicitEuler()}
