"""Force elements: spring-dampers between nodes, constant applied loads.

Spring-damper law (paper Sec. 2.1, used for every rope segment and free spring): with
``s`` the current length, ``s̄`` the rest length, ``ṡ`` the elongation rate,

    f = k (s − s̄) + c ṡ        (tension positive, acts along the segment)

``linear`` springs apply ``f`` both ways (they push when compressed); ``tension_only``
springs (real ropes) apply ``max(f, 0)`` while taut (``s > s̄``) and nothing while slack.
A zero-length segment gives zero force with finite gradients (no NaN).

Gravity is not a force here: it is added to the accelerations in ``mysim_jax.sim``.
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.dynamics.markers import scatter_rows, take_rows
from mysim_jax.core.types import Params, Scene


@struct.dataclass
class Loads:
    """Forces of one force stage, before they are turned into accelerations."""

    node_force: jnp.ndarray    # (n_nodes, 3) world frame, at points / markers (anchors: ignored)
    body_force: jnp.ndarray    # (n_bodies, 3) world frame, at the centre of mass
    body_torque: jnp.ndarray   # (n_bodies, 3) body frame

    @classmethod
    def of_nodes(cls, node_force, n_bodies: int) -> "Loads":
        zeros = jnp.zeros((n_bodies, 3), dtype=node_force.dtype)
        return cls(node_force=node_force, body_force=zeros, body_torque=zeros)

    @classmethod
    def on_bodies(cls, force, bodies, n_nodes: int, n_bodies: int) -> "Loads":
        """Forces ``(len(bodies), 3)`` (world frame, at the centres of mass) added to the
        bodies ``bodies``; no node forces, no torques."""
        dtype = force.dtype
        return cls(node_force=jnp.zeros((n_nodes, 3), dtype=dtype),
                   body_force=jnp.zeros((n_bodies, 3), dtype=dtype).at[bodies].add(force),
                   body_torque=jnp.zeros((n_bodies, 3), dtype=dtype))

    def __add__(self, other: "Loads") -> "Loads":
        return Loads(self.node_force + other.node_force, self.body_force + other.body_force,
                     self.body_torque + other.body_torque)


# fn(scene, params, phys, (node_pos, node_vel), inputs) -> Loads
ForceStage = Callable[..., Loads]


def spring_tension(stiffness, damping, rest_length, length, rate, tension_only, smooth_backward=None):
    """Scalar tension ``(n_springs,)`` of each spring; ``tension_only`` is a static bool mask.
    ``smooth_backward`` ``(tension [N], slack [m])`` (static; ``sim.smooth_backward``) keeps
    these values and gives the tension-only springs the reverse-mode gradients of a
    smoothed law (:func:`_taut_smoothed`)."""
    tension = stiffness * (length - rest_length) + damping * rate
    mask = np.asarray(tension_only, dtype=bool)
    if not mask.any():
        return tension
    if smooth_backward is None:
        taut = jnp.where(length > rest_length, jnp.maximum(tension, 0.0), 0.0)
    else:
        k, c, r = (jnp.broadcast_to(x, length.shape) for x in (stiffness, damping, rest_length))
        taut = _taut_smoothed(tuple(float(w) for w in smooth_backward), k, c, r, length, rate)
    if mask.all():
        return taut
    return jnp.where(mask, taut, tension)


def _smooth_taut(widths, k, c, r, length, rate):
    """The smoothed tension-only law whose gradients :func:`_taut_smoothed` uses:
    ``w_T softplus(T_lin / w_T) sigmoid((l - l0) / w_l)``."""
    w_tension, w_slack = widths
    linear = k * (length - r) + c * rate
    return w_tension * jax.nn.softplus(linear / w_tension) * jax.nn.sigmoid((length - r) / w_slack)


@partial(jax.custom_vjp, nondiff_argnums=(0,))
def _taut_smoothed(widths, k, c, r, length, rate):
    """The exact tension-only law (forward) with :func:`_smooth_taut`'s reverse-mode gradients."""
    linear = k * (length - r) + c * rate
    return jnp.where(length > r, jnp.maximum(linear, 0.0), 0.0)


def _taut_smoothed_fwd(widths, k, c, r, length, rate):
    return _taut_smoothed(widths, k, c, r, length, rate), (k, c, r, length, rate)


def _taut_smoothed_bwd(widths, inputs, g):
    _, vjp = jax.vjp(partial(_smooth_taut, widths), *inputs)
    return vjp(g)


_taut_smoothed.defvjp(_taut_smoothed_fwd, _taut_smoothed_bwd)


def spring_forces(scene: Scene, params: Params, node_pos, node_vel):
    """Forces ``(n_nodes, 3)`` that all springs exert on the nodes they join."""
    a = np.asarray(scene.spring_node_a, dtype=np.int32)
    b = np.asarray(scene.spring_node_b, dtype=np.int32)
    take = take_rows if scene.gather == "slices" else (lambda x, index: x[index])
    dx = take(node_pos, b) - take(node_pos, a)
    dv = take(node_vel, b) - take(node_vel, a)
    length, unit = vecmath.safe_unit(dx)
    rate = vecmath.dot(dv, unit)
    tension = spring_tension(
        params.spring_stiffness, params.spring_damping, params.spring_rest_length,
        length, rate, scene.spring_tension_only, scene.smooth_backward,
    )
    f = tension[:, None] * unit        # force on node a (towards b when in tension)
    n = scene.n_nodes
    if scene.accumulate == "matmul":
        signed = np.zeros((n, a.shape[0]), dtype=np.float64)
        signed[a, np.arange(a.shape[0])] += 1.0
        signed[b, np.arange(b.shape[0])] -= 1.0
        return jnp.asarray(signed, dtype=f.dtype) @ f
    return scatter_rows(f, a, n, scene.accumulate) - scatter_rows(f, b, n, scene.accumulate)


def spring_lengths(scene: Scene, node_pos):
    """Current length of every spring ``(n_springs,)``."""
    a = np.asarray(scene.spring_node_a, dtype=np.int32)
    b = np.asarray(scene.spring_node_b, dtype=np.int32)
    return vecmath.safe_norm(take_rows(node_pos, b) - take_rows(node_pos, a))
