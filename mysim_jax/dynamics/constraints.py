"""Joint constraints between markers, with Baumgarte stabilisation (paper Appendix A).

Constraint rows for a joint between frame I (``r_I``, axes ``x_I, y_I, z_I``) and J:

* ``fixed``:     ``r_I − r_J = 0``, ``x_I·y_J = 0``, ``x_I·z_J = 0``, ``y_I·z_J = 0``  (6 rows)
* ``universal``: ``r_I − r_J = 0``, ``z_I·z_J = 0``                            (4 rows)

A frame is a marker on a rigid body or a fixed anchor.

Dynamics (paper Eq. MBDwithoutCollision), per connected group of constrained bodies::

    M u̇ + Gᵀ λ = F,      G u̇ = −Ġu − 2α Ċ − β² C

with ``u = (v_world, ω_body)`` per body, ``G = ∂C/∂(δp, δθ)`` the velocity Jacobian
(``δθ`` a body-frame rotation increment, ``q ← q ⊗ exp(½δθ)``), and ``Ġu`` the constraint
acceleration at zero generalised acceleration. Both are computed by forward-mode autodiff
of the constraint function, so adding a joint type means writing its rows only.

The system is solved by the Schur complement ``(G M⁻¹ Gᵀ) λ = G a₀ − rhs`` with
``a₀ = M⁻¹F`` the unconstrained accelerations — one small dense solve per connected
group, never one dense system for the whole scene. Groups of identical structure are
stacked in a :class:`~mysim_jax.core.types.JointBucket` and solved with ``vmap``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import vecmath
from mysim_jax.dynamics.quaternion import quat_from_rotvec, quat_mul, quat_rotate, quat_to_matrix
from mysim_jax.core.types import JointBucket, Params, PhysState, Scene


def joint_rows(joint_type: str, pos_i, rot_i, pos_j, rot_j):
    """Constraint values of one joint; ``rot_*`` are 3x3 matrices with the axes as columns."""
    dp = pos_i - pos_j
    xi, yi, zi = rot_i[:, 0], rot_i[:, 1], rot_i[:, 2]
    yj, zj = rot_j[:, 1], rot_j[:, 2]
    if joint_type == "fixed":
        ang = jnp.stack([vecmath.dot(xi, yj), vecmath.dot(xi, zj), vecmath.dot(yi, zj)])
    elif joint_type == "universal":
        ang = vecmath.dot(zi, zj)[None]
    else:  # pragma: no cover - config validation rejects other types
        raise ValueError(f"unknown joint type {joint_type!r}")
    return jnp.concatenate([dp, ang])


def _bucket_constraint_fn(bucket: JointBucket):
    """Return ``C(pos (k,3), quat (k,4), frames) -> (n_rows,)`` for one group of a bucket."""

    def constraint(pos, quat, frames):
        rows = []
        for jt, t in enumerate(bucket.joint_types):
            sides = []
            for is_anchor, local, (f_pos, f_quat) in (
                (bucket.side_i_is_anchor[jt], bucket.side_i_local_body[jt], frames["i"]),
                (bucket.side_j_is_anchor[jt], bucket.side_j_local_body[jt], frames["j"]),
            ):
                if is_anchor:
                    sides.append((f_pos[jt], quat_to_matrix(f_quat[jt])))
                else:
                    q = quat[local]
                    sides.append((pos[local] + quat_rotate(q, f_pos[jt]),
                                  quat_to_matrix(quat_mul(q, f_quat[jt]))))
            rows.append(joint_rows(t, sides[0][0], sides[0][1], sides[1][0], sides[1][1]))
        return jnp.concatenate(rows)

    return constraint


def _frame_data(bucket: JointBucket, params: Params, side: str):
    """Per-group frame offsets ``(G, n_joints, 3)`` and quats ``(G, n_joints, 4)``."""
    is_anchor = bucket.side_i_is_anchor if side == "i" else bucket.side_j_is_anchor
    index = np.asarray(bucket.group_frame_i if side == "i" else bucket.group_frame_j, dtype=np.int32)
    anchor = np.asarray(is_anchor, dtype=bool)[None, :]
    m_idx = np.where(anchor, 0, index)
    a_idx = np.where(anchor, index, 0)
    if params.marker_pos.shape[0] == 0:
        return params.anchor_pos[a_idx], params.anchor_quat[a_idx]
    if params.anchor_pos.shape[0] == 0:
        return params.marker_pos[m_idx], params.marker_quat[m_idx]
    pos = jnp.where(anchor[..., None], params.anchor_pos[a_idx], params.marker_pos[m_idx])
    quat = jnp.where(anchor[..., None], params.anchor_quat[a_idx], params.marker_quat[m_idx])
    return pos, quat


def constraint_terms(bucket: JointBucket, pos, quat, vel, angvel, frames):
    """For one group: ``C``, velocity Jacobian ``G (n_rows, k*6)``, ``Ċ`` and ``Ġu``."""
    c_fn = _bucket_constraint_fn(bucket)
    k = pos.shape[0]

    def perturbed(delta):
        delta = delta.reshape(k, 6)
        return c_fn(pos + delta[:, :3], quat_mul(quat, quat_from_rotvec(delta[:, 3:])), frames)

    zero = jnp.zeros((k * 6,), dtype=pos.dtype)
    c_val = c_fn(pos, quat, frames)
    jac = jax.jacfwd(perturbed)(zero)

    def along_path(s):
        return c_fn(pos + s * vel, quat_mul(quat, quat_from_rotvec(s * angvel)), frames)

    def first(s):
        return jax.jvp(along_path, (s,), (jnp.ones_like(s),))[1]

    s0 = jnp.zeros((), dtype=pos.dtype)
    c_dot, c_ddot = jax.jvp(first, (s0,), (jnp.ones_like(s0),))
    return c_val, jac, c_dot, c_ddot


def constraint_error(scene: Scene, params: Params, phys: PhysState):
    """Concatenated constraint values of all joints (for drift monitoring): ``(n_rows,)``."""
    out = []
    for bucket in scene.joint_buckets:
        idx = np.asarray(bucket.group_bodies, dtype=np.int32)
        frames = {"i": _frame_data(bucket, params, "i"), "j": _frame_data(bucket, params, "j")}
        c_fn = _bucket_constraint_fn(bucket)
        vals = jax.vmap(c_fn)(phys.body_pos[idx], phys.body_quat[idx], frames)
        out.append(vals.reshape(-1))
    if not out:
        return jnp.zeros((0,), dtype=phys.body_pos.dtype)
    return jnp.concatenate(out)


def solve_constraints(scene: Scene, params: Params, phys: PhysState, acc, angacc, inertia_inv):
    """Correct free-body accelerations ``acc, angacc (n_bodies, 3)`` for all joints."""
    alpha, beta = params.baumgarte_alpha, params.baumgarte_beta
    for bucket in scene.joint_buckets:
        idx = np.asarray(bucket.group_bodies, dtype=np.int32)     # (G, k)
        frames = {"i": _frame_data(bucket, params, "i"), "j": _frame_data(bucket, params, "j")}

        def solve_group(pos, quat, vel, angvel, a_lin, a_ang, inv_m, inv_j, frames):
            c, jac, c_dot, c_ddot = constraint_terms(bucket, pos, quat, vel, angvel, frames)
            k = pos.shape[0]
            a0 = jnp.concatenate([a_lin, a_ang], axis=-1).reshape(-1)        # (6k,)
            rhs = -c_ddot - 2.0 * alpha * c_dot - beta * beta * c
            jac_b = jac.reshape(-1, k, 6)
            # M⁻¹ Gᵀ, body by body: translation 1/m, rotation J⁻¹
            minv_gt_lin = jac_b[:, :, :3] * inv_m[None, :, None]
            minv_gt_ang = jnp.einsum("kab,rkb->rka", inv_j, jac_b[:, :, 3:])
            minv_gt = jnp.concatenate([minv_gt_lin, minv_gt_ang], axis=-1).reshape(jac.shape[0], -1)
            schur = jac @ minv_gt.T
            lam = jnp.linalg.solve(schur, jac @ a0 - rhs)
            a = (a0 - minv_gt.T @ lam).reshape(k, 6)
            return a[:, :3], a[:, 3:]

        new_lin, new_ang = jax.vmap(solve_group)(
            phys.body_pos[idx], phys.body_quat[idx], phys.body_vel[idx], phys.body_angvel[idx],
            acc[idx], angacc[idx], 1.0 / params.body_mass[idx], inertia_inv[idx], frames,
        )
        acc = acc.at[idx].set(new_lin)
        angacc = angacc.at[idx].set(new_ang)
    return acc, angacc
