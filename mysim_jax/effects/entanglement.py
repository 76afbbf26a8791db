"""Entanglement: an evading drone loses its propulsion once its rotors touch the net's
lines (an effect, see docs/effects.md).

Net-based counter-drone systems (launched nets such as SkyWall, drone-carried nets such
as Fortem's DroneHunter) do not need to hold a drone by its frame: lines that reach its
spinning rotors wrap around them and stall them, and the drone loses lift. That is the
physics modelled here, at the level of the target's sphere (which stands for the drone
with its rotors):

* the rotors **touch** a line while the target's centre is within its radius plus
  ``margin`` of one of the net's line segments (the target–line capsules of the scene's
  contact, :func:`mysim_jax.contact.forces.capsule_geometry`);
* the **entanglement** ``e`` in [0, 1] grows at ``1 / time`` per second of touching and
  never decreases (a wrapped rotor stays wrapped): ``e ← min(1, e + dt / time)`` on each
  environment step (``sim.dt``) that begins touching;
* the **propulsion** keeps the fraction ``1 − e`` of its force: the target's commanded
  force ``m (a_cmd − g)`` (:mod:`mysim_jax.effects.target`) becomes ``(1 − e) m (a_cmd − g)``,
  so a fully entangled drone neither hovers nor manoeuvres and drops into the net.

The linear loss with contact time is this project's choice (a single time constant, no
rotor-by-rotor state), not a published law; ``time`` sets how long a line must stay on
the rotors, ``time: 0`` is not allowed (use a small value for an instant loss).

Configured by ``target.entanglement`` (:class:`mysim_jax.config.capture.EntanglementConfig`);
a scene without it has no entanglement memory, update or cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.contact.forces import capsule_geometry, sphere_kinematics
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.markers import node_states


@dataclass(frozen=True)
class EntanglementScene:
    """Static part: which sphere–capsule pairs are the target against the net's lines."""

    pairs: tuple[int, ...]        # indices into the scene's sphere–capsule pair table


@struct.dataclass
class EntanglementParams:
    time: jnp.ndarray             # () s of line contact for a full loss of propulsion
    margin: jnp.ndarray           # () m beyond the target's radius that the rotors reach


@struct.dataclass
class EntanglementMemory:
    level: jnp.ndarray            # () in [0, 1]: the share of propulsion lost
    touching: jnp.ndarray         # () bool: the rotors touched a line at the last step's start


def rotors_touch_lines(scene, params, phys):
    """``()`` bool: is the target within its radius plus ``margin`` of a net line?"""
    static = ENTANGLEMENT.static(scene)
    pos, _, _ = sphere_kinematics(scene, phys)
    node_pos, _ = node_states(scene, params, phys)
    depth = capsule_geometry(scene, params, pos, node_pos, np.asarray(static.pairs, np.int32))[4]
    return jnp.max(depth) >= -ENTANGLEMENT.params(params).margin


def propulsion_share(scene, state):
    """``()`` the share of its propulsion the target keeps, ``1 − e``; None in a scene
    without entanglement (the propulsion is whole and nothing is traced)."""
    if not ENTANGLEMENT.in_scene(scene):
        return None
    return 1.0 - ENTANGLEMENT.memory(state).level


class _Entanglement(Effect[EntanglementScene, EntanglementParams, EntanglementMemory]):
    name = "entanglement"

    def build(self, config, ctx):
        target = config.target
        if target is None or target.entanglement is None:
            return None
        cs, body = ctx.contact, ctx.body_names.index(target.name)
        sphere = ([len(cs.sphere_point) + i for i, b in enumerate(cs.sphere_body) if b == body]
                  if cs is not None else [])
        pairs = tuple(int(k) for k in np.flatnonzero(np.isin(np.asarray(cs.capsule_pair_sphere, int), sphere))) \
            if sphere else ()
        if not pairs:
            raise ValueError("target.entanglement: the target's rotors tangle in net lines, and the scene has no "
                             "contact between the target and line segments (add a [target, lines] pair to "
                             "contact.pairs with a group of `segments:`)")
        e = target.entanglement
        params = EntanglementParams(time=jnp.asarray(e.time, ctx.dtype), margin=jnp.asarray(e.margin, ctx.dtype))
        memory = EntanglementMemory(level=jnp.zeros((), ctx.dtype), touching=jnp.asarray(False))
        return EntanglementScene(pairs=pairs), params, memory

    def update(self, scene, params, state):
        memory = self.memory(state)
        touching = rotors_touch_lines(scene, params, state.phys)
        step = jnp.asarray(scene.dt, memory.level.dtype) / self.params(params).time
        level = jnp.minimum(1.0, memory.level + jnp.where(touching, step, 0.0))
        return None, EntanglementMemory(level=level, touching=touching)


ENTANGLEMENT = _Entanglement()
