"""Effects are plugins: a new force with settings of its own is one module (docs/effects.md:
``name``, its YAML block's ``schema``, ``build``, ``update``, ``stages``; the base class
:class:`mysim_jax.core.effect.Effect` gives the rest) and one registry entry: a library
effect's ``"name": "module:OBJECT"`` line in :data:`mysim_jax.config.effect_blocks.EFFECTS`,
or :func:`mysim_jax.effects.registry.register` for an effect object. The config layer,
the builder, the step and the types are not edited. This file adds a toy effect
(``tests/toy_effect.py``) both ways: its block validates with the scene (a bad value is a
one-line error naming the field, before anything is built), its settings reach the
effect, and the motion it causes matches the closed form."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict, dump_config
from mysim_jax.core.effect import Effect
from mysim_jax.effects import registry
from mysim_jax.sim import rollout
from toy_effect import PUSH, Push, PushConfig

pytestmark = pytest.mark.float64

ROOT = Path(__file__).resolve().parents[1]
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


LINE = {"toy_push": "toy_effect:PUSH"}     # the library's way: one entry, the effect's module:OBJECT path


@pytest.fixture
def registry_as_it_was():
    saved = dict(registry.EFFECTS)
    yield
    registry.EFFECTS.clear()
    registry.EFFECTS.update(saved)


@pytest.fixture
def push(registry_as_it_was):
    """The toy effect registered by one line, as the library registers its effects: an
    entry of the registry table (the registry as it was afterwards)."""
    registry.EFFECTS.update(LINE)                                   # the one registry line
    return PUSH


@pytest.fixture
def push_registered(registry_as_it_was):
    """The toy effect registered by one line, as a user's plugin is: ``register``."""
    registry.register(PUSH)                                         # the one registry line
    return PUSH


@pytest.mark.parametrize("way", ["push", "push_registered"])
def test_a_registered_toy_effect_moves_the_body_as_its_block_says(way, request):
    push = request.getfixturevalue(way)
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


def test_one_module_and_one_registry_line_are_all_it_takes():
    """In a fresh interpreter, the one registry line makes the toy effect's block valid.
    The entry is lazy: a file without the block validates without importing the effect's
    module (nor JAX); a file with the block imports the module, whose ``schema``
    validates it."""
    code = (
        "import sys\n"
        "sys.path.insert(0, 'tests')\n"
        "from mysim_jax.config.effect_blocks import EFFECTS\n"
        "from mysim_jax.config.scene import config_from_dict\n"
        f"EFFECTS.update({LINE!r})\n"
        "raw = {'name': 'g', 'sim': {'t_end': 1.0, 'dt': 0.01, 'output_dt': 0.1},"
        " 'bodies': [{'name': 'ball', 'mass': 1.0, 'inertia': [0.1, 0.1, 0.1]}]}\n"
        "config_from_dict(raw)\n"
        "assert 'toy_effect' not in sys.modules and 'jax' not in sys.modules, 'imported without the block'\n"
        "c = config_from_dict(dict(raw, effects={'toy_push': {'body': 'ball', 'force': [0, 0, 1]}}))\n"
        "assert 'toy_effect' in sys.modules\n"
        "assert type(c.effects['toy_push']).__name__ == 'PushConfig' and c.effects['toy_push'].force == (0, 0, 1)\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]


def test_a_name_is_registered_once(push):
    class Other(Push):
        pass
    with pytest.raises(ValueError, match="'toy_push' is registered already"):
        registry.register(Other())
    registry.register(PUSH)                 # the same effect again changes nothing
    assert registry.EFFECTS["toy_push"] is PUSH


def test_every_library_entry_is_an_effect_of_its_name():
    """Each entry of the registry table imports to an effect named as its key."""
    for name in list(registry.EFFECTS):
        effect = registry.registered_effect(name)
        assert isinstance(effect, Effect) and effect.name == name, (name, effect)


def test_an_effect_without_build_cannot_be_made():
    """``build`` is abstract: an effect that forgets it fails where it is created, before
    any scene is built."""
    class NoBuild(Effect):
        name = "no_build"

    with pytest.raises(TypeError, match="build"):
        NoBuild()
