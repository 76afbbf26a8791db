"""Effects are plugins: a new force with settings of its own is one object (docs/effects.md:
``name``, its YAML block's ``schema``, ``build``, ``update``, ``stages``; the base class
:class:`mysim_jax.core.effect.Effect` gives the rest) registered with one line
(:func:`mysim_jax.effects.registry.register`); the config layer, the builder, the step and
the types are not edited. This file adds a toy effect that way: its block validates with
the scene (a bad value is a one-line error naming the field, before anything is built),
its settings reach the effect, and the motion it causes matches the closed form."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from mysim_jax.build import build
from mysim_jax.config.effect_blocks import EFFECT_BLOCKS
from mysim_jax.config.scene import ConfigError, config_from_dict, dump_config
from mysim_jax.core.config_base import Name, StrictModel, Vec3
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads
from mysim_jax.effects import registry
from mysim_jax.sim import rollout

pytestmark = pytest.mark.float64

ROOT = Path(__file__).resolve().parents[1]


# --- the toy effect: a constant push on one body, and a count of the steps it has pushed ---


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
FORCE = [1.0, 0.0, -0.5]


def _raw(block=None, body_name="ball"):
    raw = {
        "name": "pushed",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 0.1, "integrator": "rk4", "precision": "float64"},
        "gravity": [0, 0, 0],
        "bodies": [{"name": body_name, "mass": 2.0, "inertia": [0.1, 0.1, 0.1], "vel": [0.0, 0.5, 0.0]}],
    }
    if block is not None:
        raw["effects"] = {"toy_push": block}
    return raw


@pytest.fixture
def push():
    """The toy effect registered (and the registries as they were afterwards)."""
    effects, blocks = dict(registry.EFFECTS), dict(EFFECT_BLOCKS)
    registry.register(PUSH)                                         # the one registry line
    yield PUSH
    for table, saved in ((registry.EFFECTS, effects), (EFFECT_BLOCKS, blocks)):
        table.clear()
        table.update(saved)


def test_a_registered_toy_effect_moves_the_body_as_its_block_says(push):
    config = config_from_dict(_raw({"body": "ball", "force": FORCE}))
    assert push.block(config) == PushConfig(body="ball", force=tuple(FORCE))
    scene, params, state = build(config)
    assert [name for name, _ in scene.effects] == ["toy_push"] and push.in_scene(scene)
    np.testing.assert_array_equal(np.asarray(push.params(params).force), FORCE)    # the block's value
    n = 500
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, n))(params, state)
    t = n * scene.dt
    force = np.asarray(FORCE)
    expected = np.array([0.0, 0.5, 0.0]) * t + 0.5 * force / 2.0 * t ** 2
    np.testing.assert_allclose(np.asarray(final.phys.body_pos[0]), expected, atol=2e-15)   # RK4 is exact here
    np.testing.assert_allclose(np.asarray(final.phys.body_vel[0]), [0.0, 0.5, 0.0] + force / 2.0 * t,
                               atol=2e-15)
    assert int(push.memory(final)) == n        # its update ran once per step, its memory kept


@pytest.mark.parametrize("block", [None, {"body": "other", "force": FORCE}])
def test_a_scene_without_the_block_or_its_body_carries_none_of_it(push, block):
    scene, params, state = build(config_from_dict(_raw(block)))
    assert scene.effects == () and not push.in_scene(scene)
    assert push.memory_or_none(state) is None and push.name not in params.effects
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, 10))(params, state)
    np.testing.assert_allclose(np.asarray(final.phys.body_vel[0]), [0.0, 0.5, 0.0], atol=1e-15)


@pytest.mark.parametrize("block, message", [
    ({"body": "ball", "force": [1.0, "x", 0.0]}, "effects.toy_push.force.1: Input should be a valid number"),
    ({"body": "ball", "force": [1.0, 0.0]}, "effects.toy_push.force: too few entries"),
    ({"body": "ball", "colour": "red"}, "effects.toy_push.colour: unknown key"),
    ({"force": FORCE}, "effects.toy_push.body: Field required"),
])
def test_a_bad_block_is_a_one_line_error_naming_the_field(push, block, message):
    with pytest.raises(ConfigError) as err:
        config_from_dict(_raw(block))
    lines = str(err.value).splitlines()
    assert len(lines) == 2 and lines[1].strip().startswith(message), str(err.value)   # source line, the error


def test_an_unregistered_effect_is_an_unknown_key():
    with pytest.raises(ConfigError, match=r"effects\.toy_push: unknown key"):
        config_from_dict(_raw({"body": "ball"}))


def test_the_block_round_trips_and_takes_overrides(push):
    config = config_from_dict(_raw({"body": "ball", "force": FORCE}), overrides=["effects.toy_push.force=[0, 0, 2]"])
    assert push.block(config).force == (0.0, 0.0, 2.0)
    again = config_from_dict(__import__("yaml").safe_load(dump_config(config)))
    assert push.block(again) == push.block(config)


def test_a_schema_given_by_its_path_is_imported_when_a_file_has_the_block():
    """A block's schema may be listed as ``"module:Class"``: validating a file imports that
    module, and nothing of JAX when the module has none (as the config layer has none)."""
    code = (
        "import sys\n"
        "from mysim_jax.config.effect_blocks import EFFECT_BLOCKS\n"
        "from mysim_jax.config.scene import config_from_dict\n"
        "EFFECT_BLOCKS['gust'] = 'mysim_jax.config.capture:Range'\n"
        "c = config_from_dict({'name': 'g', 'sim': {'t_end': 1.0, 'dt': 0.01, 'output_dt': 0.1},"
        " 'effects': {'gust': {'low': 0.5, 'high': 1.0}}})\n"
        "assert c.effects['gust'].high == 1.0, c.effects\n"
        "assert 'jax' not in sys.modules, 'jax imported'\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]


def test_a_name_is_registered_once(push):
    class Other(Push):
        pass
    with pytest.raises(ValueError, match="'toy_push' is registered already"):
        registry.register(Other())
    registry.register(PUSH)                 # the same effect again changes nothing
    assert registry.EFFECTS["toy_push"] is PUSH


def test_every_effect_with_a_block_has_its_schema_in_the_config_registry():
    """A library effect with a YAML block lists its schema (or its path) in EFFECT_BLOCKS,
    so that a file with the block validates without importing the effect."""
    missing = [name for name, effect in registry.EFFECTS.items()
               if effect.schema is not None and EFFECT_BLOCKS.get(name) != effect.schema]
    assert not missing, missing


def test_an_effect_without_build_cannot_be_made():
    """``build`` is abstract: an effect that forgets it fails where it is created, before
    any scene is built."""
    class NoBuild(Effect):
        name = "no_build"

    with pytest.raises(TypeError, match="build"):
        NoBuild()
