"""Two-axis camera gimbal: a universal joint whose two angles are driven by a PD servo.

The joint (paper Eq. appendix_universal, :mod:`mysim_jax.dynamics.constraints`) joins
marker ``I`` on the UAV and marker ``J`` on the camera: ``r_I = r_J``, ``z_I · z_J = 0``.
Its two free rotations are about ``z_I`` (the *outer* axis, fixed in the UAV) and about
``z_J`` (the *inner* axis, fixed in the camera). The relative orientation is written

    R_Iᵀ R_J = R_z(a₁) R₀ R_z(a₂),      R₀ = R_y(π/2)  (maps z to x)

so ``z_J`` seen from ``I`` is ``(cos a₁, sin a₁, 0)`` and ``z_I`` seen from ``J`` is
``(−cos a₂, sin a₂, 0)``: ``a₁ = atan2(R[1,2], R[0,2])``, ``a₂ = atan2(R[2,1], −R[2,0])``
with ``R = R_Iᵀ R_J``. Their rates are the relative angular velocity along the two axes,
``ȧ₁ = (ω_J − ω_I)·z_I`` and ``ȧ₂ = (ω_J − ω_I)·z_J`` (exact while ``z_I ⊥ z_J``).

Servo (a force element, not a driven constraint; the effect
:mod:`mysim_jax.effects.gimbal_servo`): motor torques ``τ_k = kp_k wrap(a_k,cmd − a_k) −
kd_k ȧ_k`` act on the camera as ``τ₁ z_I + τ₂ z_J`` and on the UAV as the opposite; the
joint's constraint forces do the rest. A force element keeps the joint a plain universal
joint (four constraint rows, the same Baumgarte stabilisation as any other joint) and
gives a physical servo with finite bandwidth. This module is the geometry both need.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mysim_jax.core import vecmath
from mysim_jax.dynamics.quaternion import quat_mul, quat_rotate, quat_to_matrix


def gimbal_frames(scene, params, phys, marker_i, marker_j):
    """``(body I, body J, R_I, R_J)`` of the gimbals joining markers ``marker_i`` (on the
    UAV) and ``marker_j`` (on the camera), each ``(n_gimbals,)``: the bodies' indices and
    the markers' world frames ``(n_gimbals, 3, 3)``."""
    mi = np.asarray(marker_i, dtype=np.int32)
    mj = np.asarray(marker_j, dtype=np.int32)
    bi = np.asarray(scene.marker_body, dtype=np.int32)[mi]
    bj = np.asarray(scene.marker_body, dtype=np.int32)[mj]
    rot_i = quat_to_matrix(quat_mul(phys.body_quat[bi], params.marker_quat[mi]))
    rot_j = quat_to_matrix(quat_mul(phys.body_quat[bj], params.marker_quat[mj]))
    return bi, bj, rot_i, rot_j


def angles_from_frames(rot_i, rot_j):
    """Gimbal angles ``(…, 2)`` from the world frames ``(…, 3, 3)`` of markers I and J."""
    rel = jnp.einsum("...ki,...kj->...ij", rot_i, rot_j)
    a1 = jnp.arctan2(rel[..., 1, 2], rel[..., 0, 2])
    a2 = jnp.arctan2(rel[..., 2, 1], -rel[..., 2, 0])
    return jnp.stack([a1, a2], axis=-1)


def gimbal_state(scene, params, phys, marker_i, marker_j):
    """Angles ``(n_gimbals, 2)`` and angle rates ``(n_gimbals, 2)`` of the gimbals joining
    markers ``marker_i`` and ``marker_j``."""
    bi, bj, rot_i, rot_j = gimbal_frames(scene, params, phys, marker_i, marker_j)
    w_i = quat_rotate(phys.body_quat[bi], phys.body_angvel[bi])
    w_j = quat_rotate(phys.body_quat[bj], phys.body_angvel[bj])
    rel = w_j - w_i
    rates = jnp.stack([vecmath.dot(rel, rot_i[..., 2]), vecmath.dot(rel, rot_j[..., 2])], axis=-1)
    return angles_from_frames(rot_i, rot_j), rates
