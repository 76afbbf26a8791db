"""Newton-Euler equations of free rigid bodies and point masses.

Translation (world frame): ``m dv/dt = F``.
Rotation (body frame):     ``J dω/dt = τ − ω × (J ω)``  (paper: dω/dt = J⁻¹(τ − ω̃Jω)).
Attitude kinematics ``dΛ/dt = ½ Λ ⊗ ω`` live in :mod:`mysim_jax.dynamics.quaternion`.
"""

from __future__ import annotations

import jax.numpy as jnp

from mysim_jax.core import vecmath


def inertia_inverse(inertia):
    """Inverse of body inertia matrices ``(..., 3, 3)`` (closed form, :func:`vecmath.inv3`)."""
    return vecmath.inv3(inertia)


def body_accelerations(mass, inertia_inv, inertia, angvel, force, torque):
    """Linear ``(n, 3)`` (world) and angular ``(n, 3)`` (body) accelerations of free bodies."""
    acc = force / mass[:, None]
    j_omega = jnp.einsum("nij,nj->ni", inertia, angvel)
    angacc = jnp.einsum("nij,nj->ni", inertia_inv, torque - vecmath.cross(angvel, j_omega))
    return acc, angacc
