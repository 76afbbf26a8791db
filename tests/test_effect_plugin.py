"""Effects are plugins: a new force is one object with ``name``, ``build``, ``update``,
``init`` and ``stages`` (docs/effects.md) plus one entry in the registry
(:data:`mysim_jax.effects.registry.EFFECTS`); the builder, the step and the types are not
edited. This file adds a toy effect that way and checks the motion it causes against the
closed form."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.dynamics.forces import Loads
from mysim_jax.effects import registry
from mysim_jax.sim import rollout

pytestmark = pytest.mark.float64


# --- the toy effect: a constant push on one body, and a count of the steps it has pushed ---


@dataclass(frozen=True)
class PushScene:
    body: int                        # index of the pushed body


@struct.dataclass
class PushParams:
    force: jnp.ndarray               # (3,) N, world frame


class Push:
    """Pushes the body named ``body`` with ``force`` (N, world frame) while the scene has it."""

    name = "toy_push"

    def __init__(self, body: str, force):
        self.body, self.force = body, np.asarray(force, float)

    def build(self, config, ctx):
        if self.body not in ctx.body_names:
            return None                                   # not in this scene: nothing is traced
        return (PushScene(body=ctx.body_names.index(self.body)),
                PushParams(force=jnp.asarray(self.force, ctx.dtype)), jnp.zeros((), jnp.int32))

    def update(self, scene, params, state):
        # what the stage holds over the step's sub-steps, and the new memory
        return params.effects[self.name].force, state.effects[self.name] + 1

    def init(self, scene, params, state):
        return state

    def stages(self, static):
        def push(scene, params, phys, nodes, held):
            body_force = jnp.zeros((scene.n_bodies, 3), held.dtype).at[static.body].set(held)
            zeros = jnp.zeros((scene.n_bodies, 3), held.dtype)
            return Loads(node_force=jnp.zeros((scene.n_nodes, 3), held.dtype), body_force=body_force,
                         body_torque=zeros)
        return (("toy_push", push),)


def _scene(body_name="ball"):
    return config_from_dict({
        "name": "pushed",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 0.1, "integrator": "rk4", "precision": "float64"},
        "gravity": [0, 0, 0],
        "bodies": [{"name": body_name, "mass": 2.0, "inertia": [0.1, 0.1, 0.1], "vel": [0.0, 0.5, 0.0]}],
    })


@pytest.fixture
def push(monkeypatch):
    effect = Push("ball", [1.0, 0.0, -0.5])
    monkeypatch.setitem(registry.EFFECTS, effect.name, effect)      # the one registry line
    return effect


def test_a_registered_toy_effect_moves_the_body_as_the_closed_form_says(push):
    scene, params, state = build(_scene())
    assert [name for name, _ in scene.effects] == ["toy_push"]
    n = 500
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, n))(params, state)
    t = n * scene.dt
    expected = np.array([0.0, 0.5, 0.0]) * t + 0.5 * push.force / 2.0 * t ** 2
    np.testing.assert_allclose(np.asarray(final.phys.body_pos[0]), expected, atol=2e-15)   # RK4 is exact here
    np.testing.assert_allclose(np.asarray(final.phys.body_vel[0]), [0.0, 0.5, 0.0] + push.force / 2.0 * t,
                               atol=2e-15)
    assert int(final.effects["toy_push"]) == n        # its update ran once per step, its memory kept


def test_a_scene_without_the_effects_subject_carries_none_of_it(push):
    scene, params, state = build(_scene(body_name="other"))
    assert scene.effects == ()
    assert "toy_push" not in params.effects and "toy_push" not in state.effects
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, 10))(params, state)
    np.testing.assert_allclose(np.asarray(final.phys.body_vel[0]), [0.0, 0.5, 0.0], atol=1e-15)
