"""A hand-written batch-last kernel of a rope network: the speed the library is held to.

The benchmark compares the library's batched rollout against this kernel in the same run
(``scripts/bench.py``, section a). It is the same physics as :func:`mysim_jax.sim.step`
for a scene of point masses joined by linear or tension-only springs, with fixed anchors,
gravity and semi-implicit Euler — written the way one would write it by hand for speed on
a CPU: every node is its own ``(3, B)`` array with the batch as the contiguous last axis,
every spring a few element-wise operations on two such arrays, every node force a plain
sum of its springs' forces. There is no ``vmap``, no gather and no scatter: the topology is
unrolled in Python when the kernel is traced.

It is deliberately separate code (it shares nothing with the library's force pipeline
but the built Scene's topology and Params' constants), so that the benchmark can also
check that both compute the same trajectory.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np


def rope_net_kernel(scene, params, n_steps: int) -> Callable:
    """``run(pos, vel) -> (pos, vel)``: ``n_steps`` semi-implicit Euler steps of ``h =
    scene.substep`` for B environments at once. ``pos`` and ``vel`` are lists of
    ``n_points`` arrays ``(3, B)``. Params are per-scene constants (shared by all B).

    Raises ValueError for scenes outside the kernel's physics (bodies, markers, contact,
    quadrotors, effects, applied loads, another integrator).
    """
    if scene.n_bodies or scene.n_markers or scene.contact is not None or scene.quadrotor is not None \
            or scene.effects or scene.has_loads or scene.integrator != "semi_implicit_euler":
        raise ValueError("rope_net_kernel: only point masses, springs and anchors with semi-implicit Euler")
    dtype = np.dtype(scene.dtype)
    n_points = scene.n_points
    node_a = [int(i) for i in scene.spring_node_a]
    node_b = [int(i) for i in scene.spring_node_b]
    stiffness = [dtype.type(x) for x in np.asarray(params.spring_stiffness)]
    damping = [dtype.type(x) for x in np.asarray(params.spring_damping)]
    rest = [dtype.type(x) for x in np.asarray(params.spring_rest_length)]
    tension_only = [bool(x) for x in scene.spring_tension_only]
    inv_mass = [dtype.type(1.0 / x) for x in np.asarray(params.point_mass)]
    anchors = np.asarray(params.anchor_pos, dtype=dtype)
    gravity = [dtype.type(x) for x in np.asarray(params.gravity)] if scene.has_gravity else [dtype.type(0)] * 3
    h = dtype.type(scene.substep)

    def one_step(pos, vel):
        # node i < n_points is a point mass; otherwise an anchor: a constant column
        def p(i):
            return pos[i] if i < n_points else anchors[i - n_points][:, None]

        force = [None] * n_points
        for s, (ia, ib) in enumerate(zip(node_a, node_b)):
            dx = p(ib) - p(ia)
            if ia < n_points and ib < n_points:
                dv = vel[ib] - vel[ia]
            else:
                dv = vel[ib] if ib < n_points else -vel[ia]
            length = jnp.sqrt(dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2])
            inv_len = jnp.where(length > 0, 1.0 / jnp.where(length > 0, length, 1.0), 0.0)
            rate = (dv[0] * dx[0] + dv[1] * dx[1] + dv[2] * dx[2]) * inv_len
            tension = stiffness[s] * (length - rest[s]) + damping[s] * rate
            if tension_only[s]:
                tension = jnp.where(length > rest[s], jnp.maximum(tension, 0), 0)
            f = (tension * inv_len) * dx          # on node a, towards b
            if ia < n_points:
                force[ia] = f if force[ia] is None else force[ia] + f
            if ib < n_points:
                force[ib] = -f if force[ib] is None else force[ib] - f
        new_pos, new_vel = [], []
        for i in range(n_points):
            acc = jnp.stack([jnp.full_like(pos[i][0], g) for g in gravity]) if force[i] is None else \
                force[i] * inv_mass[i] + jnp.asarray(gravity, dtype)[:, None]
            v = vel[i] + h * acc
            new_vel.append(v)
            new_pos.append(pos[i] + h * v)
        return new_pos, new_vel

    def run(pos, vel):
        def body(carry, _):
            return one_step(*carry), None
        return jax.lax.scan(body, (list(pos), list(vel)), None, length=n_steps)[0]

    return run


def to_node_columns(x) -> list:
    """A batch-first ``(B, n, 3)`` array as the kernel's list of ``n`` arrays ``(3, B)``."""
    return [jnp.transpose(x[:, i, :]) for i in range(x.shape[1])]


def from_node_columns(cols) -> jnp.ndarray:
    """The kernel's list of ``(3, B)`` arrays as a batch-first ``(B, n, 3)`` array."""
    return jnp.stack([jnp.transpose(c) for c in cols], axis=1)
