"""A toy effect in one module (tests/test_effect_plugin.py): the schema of its YAML block
``effects.toy_push`` and the effect itself, a constant push on one body and a count of the
steps it has pushed. One registry entry, ``"toy_push": "toy_effect:PUSH"``, is all it
needs besides this module."""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
from flax import struct

from mysim_jax.core.config_base import Name, StrictModel, Vec3
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads


class PushConfig(StrictModel):
    """``effects.toy_push``: push the body ``body`` with ``force`` (N, world frame)."""

    body: Name
    force: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PushScene:
    body: int                        # index of the pushed body


@struct.dataclass
class PushParams:
    force: jnp.ndarray               # (3,) N, world frame


class Push(Effect[PushScene, PushParams, jnp.ndarray]):
    """Pushes the body its block names while the scene has the block and the body."""

    name = "toy_push"
    schema = PushConfig

    def build(self, config, ctx):
        block = self.block(config)
        if block is None or block.body not in ctx.body_names:
            return None                                   # not in this scene: nothing is traced
        return (PushScene(body=ctx.body_names.index(block.body)),
                PushParams(force=jnp.asarray(block.force, ctx.dtype)), jnp.zeros((), jnp.int32))

    def update(self, scene, params, state):
        # what the stage holds over the step's sub-steps, and the new memory
        return self.params(params).force, self.memory(state) + 1

    def stages(self, static):
        def push(scene, params, phys, nodes, held):
            body_force = jnp.zeros((scene.n_bodies, 3), held.dtype).at[static.body].set(held)
            zeros = jnp.zeros((scene.n_bodies, 3), held.dtype)
            return Loads(node_force=jnp.zeros((scene.n_nodes, 3), held.dtype), body_force=body_force,
                         body_torque=zeros)
        return (("toy_push", push),)


PUSH = Push()
