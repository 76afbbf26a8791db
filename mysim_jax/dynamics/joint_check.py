"""Host-side check that a scene's joints can be solved in their initial configuration.

The constraint solve (:mod:`mysim_jax.dynamics.constraints`) inverts ``G M⁻¹ Gᵀ`` per
connected group of bodies, with ``G`` the velocity Jacobian of the constraint rows. When
``G`` loses rank the solve divides by zero and the whole state turns NaN at the first
step. Two input mistakes do that:

* a joint placed in a singular configuration: a universal joint whose two z axes are
  parallel (its row ``z_I·z_J`` has the gradient ``z_I × z_J = 0``), or a fixed joint
  whose marker frames are a quarter turn apart about an axis (``x_I·y_J = 1``);
* redundant joints: two joints that constrain the same motion (two fixed joints between
  the same bodies, a closed chain that over-determines itself).

Both are found here from the config alone, in NumPy, before anything compiles. The rows
and their Jacobian follow :mod:`mysim_jax.dynamics.constraints` (body-frame rotation
increments, ``q ← q ⊗ exp(½δθ)``), re-derived in closed form:

* position rows ``r_I − r_J``: ``∂/∂δp_b = ±I``, ``∂/∂δθ_b = ∓R_b [r_b]×``;
* angular rows ``a·b`` (``a`` an axis of frame I, ``b`` of frame J):
  ``∂/∂δθ_I = R_Iᵀ (a × b)``, ``∂/∂δθ_J = R_Jᵀ (b × a)``.
"""

from __future__ import annotations

import numpy as np

from mysim_jax.core.npgeom import skew

# A joint's own rows are singular below this smallest / largest singular value (assembled
# joints sit near 1: their Jacobian rows are unit cross products and unit position rows).
SINGULAR_JOINT_RATIO = 1e-6
# A group's rows are redundant below this relative singular value (exact redundancy gives
# round-off, ~1e-16).
REDUNDANT_GROUP_RATIO = 1e-9


def _matrix(q) -> np.ndarray:
    w, x, y, z = (float(c) for c in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _frame(config, ref: str):
    """``(body index | None, R_body, offset in body frame, frame axes (3, 3) world)``."""
    for a in config.anchors:
        if a.name == ref:
            return None, None, None, _matrix(a.quat)
    body_name, _, marker_name = ref.partition(".")
    for bi, b in enumerate(config.bodies):
        if b.name == body_name:
            m = next(m for m in b.markers if m.name == marker_name)
            rot = _matrix(b.quat)
            return bi, rot, np.asarray(m.pos, float), rot @ _matrix(m.quat)
    raise KeyError(ref)        # config validation has rejected unknown references


_ANGULAR_ROWS = {"fixed": ((0, 1), (0, 2), (1, 2)), "universal": ((2, 2),)}
_AXIS = "xyz"


def joint_jacobian(config, joint) -> np.ndarray:
    """Velocity Jacobian ``(n_rows, 6 n_bodies)`` of one joint's rows (columns per body:
    ``δp`` world, ``δθ`` body frame)."""
    n = len(config.bodies)
    sides = [_frame(config, joint.marker_i), _frame(config, joint.marker_j)]
    rows = []
    for k in range(3):
        row = np.zeros(6 * n)
        for sign, (b, rot, offset, _) in zip((1.0, -1.0), sides):
            if b is not None:
                row[6 * b + k] += sign
                row[6 * b + 3:6 * b + 6] += -sign * (rot @ skew(offset))[k]
        rows.append(row)
    (bi, rot_i, _, axes_i), (bj, rot_j, _, axes_j) = sides
    for ai, aj in _ANGULAR_ROWS[joint.type]:
        a, b = axes_i[:, ai], axes_j[:, aj]
        row = np.zeros(6 * n)
        if bi is not None:
            row[6 * bi + 3:6 * bi + 6] += rot_i.T @ np.cross(a, b)
        if bj is not None:
            row[6 * bj + 3:6 * bj + 6] += rot_j.T @ np.cross(b, a)
        rows.append(row)
    return np.asarray(rows)


def _why_singular(config, joint) -> str:
    _, _, _, axes_i = _frame(config, joint.marker_i)
    _, _, _, axes_j = _frame(config, joint.marker_j)
    if joint.type == "universal":
        return (f"the z axes of '{joint.marker_i}' and '{joint.marker_j}' are parallel "
                f"(cos = {axes_i[:, 2] @ axes_j[:, 2]:.6g}); a universal joint needs them perpendicular")
    cosines = ", ".join(f"{_AXIS[a]}_I·{_AXIS[b]}_J = {axes_i[:, a] @ axes_j[:, b]:.3g}" for a, b in _ANGULAR_ROWS["fixed"])
    return (f"the frames of '{joint.marker_i}' and '{joint.marker_j}' are turned so far apart that "
            f"the fixed joint's rows lose their gradient ({cosines}; aligned frames give 0)")


def joint_groups(n_bodies: int, joint_bodies) -> dict[int, list[int]]:
    """Joints grouped by the connected set of bodies they join (anchors join nothing).

    ``joint_bodies[j]`` lists the body indices of joint ``j`` (one or two). Returns
    ``{representative body: [joint indices, in joint order]}``, groups in order of their
    first joint.
    """
    parent = list(range(n_bodies))

    def find(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for bodies in joint_bodies:
        for b in bodies[1:]:
            parent[find(b)] = find(bodies[0])
    groups: dict[int, list[int]] = {}
    for j, bodies in enumerate(joint_bodies):
        groups.setdefault(find(bodies[0]), []).append(j)
    return groups


def joint_problems(config) -> list[str]:
    """Joints that start singular, and groups of joints that are redundant, as strings
    naming the joints (empty when every group can be solved)."""
    if not config.joints:
        return []
    problems = []
    jacobians = []
    for i, joint in enumerate(config.joints):
        jac = joint_jacobian(config, joint)
        s = np.linalg.svd(jac, compute_uv=False)
        if s[-1] < SINGULAR_JOINT_RATIO * s[0]:
            problems.append(f"joints.{i} ('{joint.name}'): starts in a singular configuration: "
                            + _why_singular(config, joint))
        jacobians.append(jac)
    if problems:
        return problems
    n = len(config.bodies)
    groups = joint_groups(n, [[b for b in range(n) if np.any(jac[:, 6 * b:6 * b + 6])] for jac in jacobians])
    for members in groups.values():
        if len(members) < 2:
            continue
        stacked = np.concatenate([jacobians[i] for i in members], axis=0)
        s = np.linalg.svd(stacked, compute_uv=False)
        if stacked.shape[0] > stacked.shape[1] or s[-1] < REDUNDANT_GROUP_RATIO * s[0]:
            names = ", ".join(f"joints.{i} ('{config.joints[i].name}')" for i in members)
            problems.append(f"{names}: these joints constrain the same motion more than once "
                            "(redundant constraints make the joint solve singular); remove or loosen one")
    return problems
