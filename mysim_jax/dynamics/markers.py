"""Markers (local frames on rigid bodies) and the node table.

A marker ``m`` on body ``b`` has a body-frame offset ``r_m`` and orientation ``q_m``.
Its world position is ``p_b + R_b r_m`` and its velocity ``v_b + R_b (ω_b × r_m)``
(ω in the body frame). A force ``F`` (world) applied at the marker acts on the body as
``F`` at the centre of mass plus the body-frame torque ``r_m × (R_bᵀ F)``.

Springs, rope segments and loads address *nodes* (see :mod:`mysim_jax.core.types`): points,
markers and anchors in one table, so one gather and one scatter serve them all.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import vecmath
from mysim_jax.dynamics.quaternion import quat_rotate, quat_rotate_inv
from mysim_jax.core.types import Params, PhysState, Scene


def marker_kinematics(scene: Scene, params: Params, phys: PhysState):
    """World position ``(n_markers, 3)`` and velocity ``(n_markers, 3)`` of every marker."""
    body = np.asarray(scene.marker_body, dtype=np.int32)
    q = phys.body_quat[body]
    r_world = quat_rotate(q, params.marker_pos)
    pos = phys.body_pos[body] + r_world
    vel = phys.body_vel[body] + quat_rotate(q, vecmath.cross(phys.body_angvel[body], params.marker_pos))
    return pos, vel


def node_states(scene: Scene, params: Params, phys: PhysState):
    """Positions and velocities of all nodes (points, markers, anchors): ``(n_nodes, 3)`` each."""
    pos = [phys.point_pos]
    vel = [phys.point_vel]
    if scene.n_markers:
        with jax.named_scope("markers"):
            mpos, mvel = marker_kinematics(scene, params, phys)
        pos.append(mpos)
        vel.append(mvel)
    if scene.n_anchors:
        pos.append(params.anchor_pos)
        vel.append(jnp.zeros_like(params.anchor_pos))
    return jnp.concatenate(pos, axis=0), jnp.concatenate(vel, axis=0)


def index_runs(index) -> tuple[tuple[int, int, int, int], ...]:
    """Split a static index array into runs ``(out_start, src_start, length, stride)``.

    A run is a maximal stretch of ``index`` that counts up by one (``stride`` 1) or
    repeats one value (``stride`` 0): ``index[out_start + i] == src_start + stride * i``.
    Rope segments, contact pairs ("ball vs all net points") and marker tables are a few
    such runs, which XLA handles as slices and broadcasts instead of gathers/scatters.
    """
    index = np.asarray(index, dtype=np.int64).reshape(-1)
    runs, i, k = [], 0, index.shape[0]
    while i < k:
        j = i + 1
        stride = int(index[j] - index[i]) if j < k and index[j] - index[i] in (0, 1) else 1
        while j < k and index[j] - index[j - 1] == stride:
            j += 1
        runs.append((i, int(index[i]), j - i, stride))
        i = j
    return tuple(runs)


# Use slices while the index has at most this many runs (or at most a quarter as many
# runs as entries); beyond that the many small slices cost more than one gather.
MAX_SLICE_RUNS = 8


def _few_runs(runs, k: int) -> bool:
    return len(runs) <= max(MAX_SLICE_RUNS, k // 4)


def take_rows(x, index):
    """``x[index]`` for a static integer ``index`` ``(k,)``, as slices when it has few runs.

    Under ``vmap`` XLA:CPU lowers a gather with a constant index array to a per-element
    loop; contiguous slices and broadcasts avoid it. Which is faster depends on the host
    (BENCHMARKS.md, section f, times both side by side). Results are identical to ``x[index]``.
    """
    index = np.asarray(index, dtype=np.int32).reshape(-1)
    runs = index_runs(index)
    if not runs:
        return x[index]
    if not _few_runs(runs, index.shape[0]):
        return x[index]
    pieces = [x[s:s + n] if stride else jnp.broadcast_to(x[s:s + 1], (n,) + x.shape[1:])
              for _, s, n, stride in runs]
    return pieces[0] if len(pieces) == 1 else jnp.concatenate(pieces, axis=0)


def scatter_rows(values, index, n: int, method: str):
    """Sum rows of ``values`` ``(k, 3)`` into ``n`` rows by the static ``index`` ``(k,)``.

    ``method="segment_sum"`` uses ``jax.ops.segment_sum`` (a scatter-add; with the batch
    axis last, see :mod:`mysim_jax.core.batching`, it adds contiguous batch rows);
    ``"matmul"`` multiplies by a constant one-hot matrix. BENCHMARKS.md section (b)
    measures both.
    """
    index = np.asarray(index, dtype=np.int32).reshape(-1)
    if method == "matmul":
        onehot = np.zeros((n, index.shape[0]), dtype=np.float64)
        onehot[index, np.arange(index.shape[0])] = 1.0
        return jnp.asarray(onehot, dtype=values.dtype) @ values
    return jax.ops.segment_sum(values, index, num_segments=n)


def distribute_node_forces(scene: Scene, params: Params, phys: PhysState, node_force):
    """Split node forces ``(n_nodes, 3)`` into point forces, body forces and body torques.

    Returns ``(point_force (n_points, 3), body_force (n_bodies, 3) world,
    body_torque (n_bodies, 3) body frame)``. Forces on anchors are dropped (the world
    takes them).
    """
    npt, nm = scene.n_points, scene.n_markers
    point_force = node_force[:npt]
    if nm == 0 or scene.n_bodies == 0:
        zeros = jnp.zeros((scene.n_bodies, 3), dtype=node_force.dtype)
        return point_force, zeros, zeros
    with jax.named_scope("marker_loads"):
        f_marker = node_force[npt:npt + nm]
        body = np.asarray(scene.marker_body, dtype=np.int32)
        torque_local = vecmath.cross(params.marker_pos, quat_rotate_inv(phys.body_quat[body], f_marker))
        both = jnp.concatenate([f_marker, torque_local], axis=-1)   # one scatter for both
        summed = scatter_rows(both, body, scene.n_bodies, scene.accumulate)
    return point_force, summed[:, :3], summed[:, 3:]
