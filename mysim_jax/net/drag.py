"""Air drag on the net's lines (an effect, see docs/effects.md).

Every lumped mass of the net and its tethers carries the quadratic drag of the piece of
line it stands for (:mod:`mysim_jax.net.config`): ``F_i = −½ ρ (C_d d ℓ)_i |v_i| v_i``
in still air. The drag acts on the whole velocity, not only its component across the
line (a simplification: along a line the drag is much smaller, but a net moves mostly
across its lines).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads
from mysim_jax.net.config import net_elements


@dataclass(frozen=True)
class LineDragScene:
    points: tuple[int, ...]          # (n,) point indices of the net's masses


@struct.dataclass
class LineDragParams:
    constant: jnp.ndarray            # (n,) kg/m, ½ ρ C_d d ℓ of each mass


def _stage(scene, params, phys, nodes, held) -> Loads:
    static = LINE_DRAG.static(scene)
    idx = np.asarray(static.points, dtype=np.int32)
    v = phys.point_vel[idx]
    force = -(LINE_DRAG.params(params).constant * vecmath.safe_norm(v))[:, None] * v
    node_force = jnp.zeros((scene.n_nodes, 3), dtype=v.dtype).at[idx].set(force)
    return Loads.of_nodes(node_force, scene.n_bodies)


class _LineDrag(Effect[LineDragScene, LineDragParams, None]):
    name = "line_drag"

    def build(self, config, ctx):
        net = config.net
        if net is None or net.air_density == 0.0:
            return None

        bodies = {b.name: b for b in config.bodies}
        areas = net_elements(net, bodies, {q.body for q in config.quadrotors} & set(bodies)).drag_area
        names = [n for n in ctx.point_names if areas.get(n, 0.0) > 0.0]
        if not names:
            return None
        constant = 0.5 * net.air_density * np.asarray([areas[n] for n in names])
        static = LineDragScene(points=tuple(ctx.point_names.index(n) for n in names))
        return static, LineDragParams(constant=jnp.asarray(constant, dtype=ctx.dtype)), None

    def stages(self, static):
        return (("line_drag", _stage),)


LINE_DRAG = _LineDrag()
