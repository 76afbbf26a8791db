"""Wind on the quadrotors (an effect, see docs/effects.md): a world-frame force on each UAV
body at its centre of mass, a constant part plus one ``1 − cos`` gust,

    F(t) = force + ½ gust_force (1 − cos(2π (t − gust_start) / gust_duration))

for ``gust_start <= t <= gust_start + gust_duration`` (``quadrotors.<i>.wind``,
:class:`~mysim_jax.config.quadrotor.WindConfig`). The force is sampled once per
environment step, at its start on the controller's clock, and held over the step's
sub-steps, like the motor commands.

A scene has the effect when a quadrotor has ``wind:`` or when its environment draws a
wind force per episode (``env.randomize.wind_force``; the capture environment adds the
draw to :attr:`WindParams.force` of every UAV).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.control.pid import control_time
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads


@dataclass(frozen=True)
class WindScene:
    bodies: tuple[int, ...]          # (n_quads,) body index of each quadrotor


@struct.dataclass
class WindParams:
    """Traced wind constants, one row per quadrotor (vmap or randomise them per environment)."""

    force: jnp.ndarray               # (n_quads, 3) N, world, the constant part
    gust_force: jnp.ndarray          # (n_quads, 3) N, world, peak of the 1 − cos gust
    gust_start: jnp.ndarray          # (n_quads,) s
    gust_duration: jnp.ndarray       # (n_quads,) s


def wind_force(wp: WindParams, t):
    """World-frame wind force ``(n_quads, 3)`` at time ``t``: constant + 1 − cos gust."""
    phase = (t - wp.gust_start) / wp.gust_duration
    inside = (phase >= 0.0) & (phase <= 1.0)
    shape = jnp.where(inside, 0.5 * (1.0 - jnp.cos(2.0 * jnp.pi * jnp.clip(phase, 0.0, 1.0))), 0.0)
    return wp.force + shape[:, None] * wp.gust_force


def _stage(scene, params, phys, nodes, held) -> Loads:
    bodies = np.asarray(WIND.static(scene).bodies, dtype=np.int32)
    return Loads.on_bodies(held, bodies, scene.n_nodes, scene.n_bodies)


class _Wind(Effect[WindScene, WindParams, None]):
    name = "wind"

    def build(self, config, ctx):
        quads = config.quadrotors
        drawn = config.env is not None and config.env.randomize.wind_force is not None
        if not quads or not (drawn or any(q.wind is not None for q in quads)):
            return None
        winds = [q.wind for q in quads]

        def arr(x, shape):
            return jnp.asarray(np.asarray(x, dtype=float).reshape(shape), dtype=ctx.dtype)

        params = WindParams(force=arr([w.force if w else (0.0, 0.0, 0.0) for w in winds], (-1, 3)),
                            gust_force=arr([w.gust_force if w else (0.0, 0.0, 0.0) for w in winds], (-1, 3)),
                            gust_start=arr([w.gust_start if w else 0.0 for w in winds], (-1,)),
                            gust_duration=arr([w.gust_duration if w else 1.0 for w in winds], (-1,)))
        return WindScene(bodies=tuple(ctx.quadrotor_bodies)), params, None

    def update(self, scene, params, state):
        """The wind force held over the step, at its start on the controller's clock."""
        return wind_force(self.params(params), control_time(scene, state.controller)), None

    def stages(self, static):
        return (("wind", _stage),)


WIND = _Wind()
