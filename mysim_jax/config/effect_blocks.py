"""The registry of effects: every effect a scene may have, one entry each, in pipeline
order (:data:`EFFECTS`), and the validation of their YAML blocks.

An entry maps the effect's name to the effect itself or, for the effects of the library,
to its ``"module:OBJECT"`` path. A path is imported when the effect is first needed: by
the builder and the step (:mod:`mysim_jax.effects.registry`, which reads this same
table), or here, to validate a scene file that has the effect's block. That one entry is
all an effect needs: its module declares the rest (docs/effects.md), its YAML block's
schema included. :func:`mysim_jax.effects.registry.register` adds an effect object at
run time.

An effect with settings of its own owns a block under ``effects:`` named after it::

    effects:
      toy_push: {body: ball, force: [1.0, 0.0, -0.5]}

and declares the block's pydantic model as its ``schema``. :class:`~mysim_jax.config.scene.SceneConfig` validates the block
with :func:`validate_effect_blocks`: an unknown effect, an unknown key or a bad value is
a :class:`~mysim_jax.core.config_base.ConfigError` naming the field
(``effects.toy_push.force``), before anything is built.

Pydantic only: this module never imports JAX, and a file validates without importing any
effect unless it has an ``effects:`` block. A block of a library effect imports that
effect's module to read its schema (and whatever the module imports: JAX, for every
effect that builds arrays).
"""

from __future__ import annotations

import importlib

from pydantic import ConfigDict, create_model

from mysim_jax.core.config_base import StrictModel

# effect name -> the effect, or "module:OBJECT" of a library effect (imported on first use),
# in pipeline order. The library's effects keep their settings in the blocks they belong
# to (quadrotors.*.wind, quadrotors.*.drag, quadrotors.*.cameras, net.air_density, target,
# target.entanglement): none has an effects: block.
EFFECTS: dict[str, object] = {
    "wind": "mysim_jax.effects.wind:WIND",
    "body_drag": "mysim_jax.effects.body_drag:BODY_DRAG",
    "gimbal_servo": "mysim_jax.effects.gimbal_servo:GIMBAL_SERVO",
    "line_drag": "mysim_jax.net.drag:LINE_DRAG",
    "entanglement": "mysim_jax.effects.entanglement:ENTANGLEMENT",
    "target": "mysim_jax.effects.target:TARGET",
}


def registered_effect(name: str):
    """The effect registered as ``name`` (imported from its path on first use). A KeyError
    names an unregistered effect; a ValueError an entry whose object has another name."""
    entry = EFFECTS[name]
    if isinstance(entry, str):
        module, _, attr = entry.partition(":")
        effect = getattr(importlib.import_module(module), attr)
        if getattr(effect, "name", None) != name:
            raise ValueError(f"effect registry: {entry} is named {getattr(effect, 'name', None)!r}, "
                             f"registered as {name!r}")
        EFFECTS[name] = entry = effect
    return entry


def effect_schema(name: str) -> type[StrictModel] | None:
    """The model that validates ``effects.<name>`` (None: the effect has no block)."""
    return registered_effect(name).schema


def validate_effect_blocks(blocks: dict) -> dict:
    """``{name: validated block}`` of a raw ``effects:`` mapping. Raises pydantic's
    ValidationError located at ``<name>.<field>`` (an unregistered name, or an effect
    without a block, is an unknown key), so that the scene's error reads
    ``effects.<name>.<field>: ...``."""
    schemas = {name: effect_schema(name) for name in blocks if name in EFFECTS}
    fields = {name: (schema | None, None) for name, schema in schemas.items() if schema is not None}
    model = create_model("EffectBlocks", __config__=ConfigDict(extra="forbid", frozen=True), **fields)
    validated = model.model_validate(blocks)
    return {name: getattr(validated, name) for name in blocks}
