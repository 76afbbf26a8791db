"""Linear aerodynamic drag on the quadrotor bodies (an effect, see docs/effects.md):

    F = −R D Rᵀ v,      D = diag(drag)  (N s/m, body axes; ``quadrotors.<i>.drag``)

on each UAV body at its centre of mass, with ``R`` the body's attitude and ``v`` its
velocity in still air. A scene has the effect when a quadrotor has ``drag:`` (the others
get zero coefficients). No memory, no update: the force follows the state in every
sub-step.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads
from mysim_jax.dynamics.quaternion import quat_rotate, quat_rotate_inv


@dataclass(frozen=True)
class BodyDragScene:
    bodies: tuple[int, ...]          # (n_quads,) body index of each quadrotor


@struct.dataclass
class BodyDragParams:
    drag: jnp.ndarray                # (n_quads, 3) N s/m, body axes


def _stage(scene, params, phys, nodes, held) -> Loads:
    bodies = np.asarray(BODY_DRAG.static(scene).bodies, dtype=np.int32)
    q = phys.body_quat[bodies]
    v_body = quat_rotate_inv(q, phys.body_vel[bodies])
    force = quat_rotate(q, -BODY_DRAG.params(params).drag * v_body)
    return Loads.on_bodies(force, bodies, scene.n_nodes, scene.n_bodies)


class _BodyDrag(Effect[BodyDragScene, BodyDragParams, None]):
    name = "body_drag"

    def build(self, config, ctx):
        quads = config.quadrotors
        if not any(q.drag is not None for q in quads):
            return None
        drag = np.asarray([q.drag or (0.0, 0.0, 0.0) for q in quads], dtype=float).reshape(-1, 3)
        return (BodyDragScene(bodies=tuple(ctx.quadrotor_bodies)),
                BodyDragParams(drag=jnp.asarray(drag, dtype=ctx.dtype)), None)

    def stages(self, static):
        return (("body_drag", _stage),)


BODY_DRAG = _BodyDrag()
