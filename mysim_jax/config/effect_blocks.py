"""The registry of effect schemas: which keys the ``effects:`` block of a scene file may
have, and the pydantic model that validates each.

An effect with settings of its own (docs/effects.md) owns a block under ``effects:``
named after it::

    effects:
      toy_push: {body: ball, force: [1.0, 0.0, -0.5]}

and declares the block's model as its ``schema``. :data:`EFFECT_BLOCKS` maps the effect's
name to that model, or to its ``"module:Class"`` path, imported only when a scene file has
the block (keep that module free of JAX, as this layer is, and validating a file stays
free of JAX). :func:`mysim_jax.effects.registry.register` fills both registries from the
effect in one line; an effect shipped with the library whose block must validate without
JAX also lists its schema's path here. :class:`~mysim_jax.config.scene.SceneConfig`
validates the block with :func:`validate_effect_blocks`: an unknown effect, an unknown key
or a bad value is a :class:`~mysim_jax.core.config_base.ConfigError` naming the field
(``effects.toy_push.force``), before anything is built.

Pydantic only: this module never imports JAX.
"""

from __future__ import annotations

import importlib

from pydantic import ConfigDict, create_model

from mysim_jax.core.config_base import StrictModel

# effect name -> its YAML block's schema: a pydantic model, or "module:Class" of one.
# The effects shipped with the library keep their settings in the blocks they belong to
# (contact.broad_phase, target, target.entanglement, net.air_density), so none is listed.
EFFECT_BLOCKS: dict[str, object] = {}


def effect_schema(name: str) -> type[StrictModel]:
    """The model that validates ``effects.<name>`` (imported from its path on first use)."""
    schema = EFFECT_BLOCKS[name]
    if isinstance(schema, str):
        module, _, attr = schema.partition(":")
        schema = getattr(importlib.import_module(module), attr)
    return schema


def validate_effect_blocks(blocks: dict) -> dict:
    """``{name: validated block}`` of a raw ``effects:`` mapping. Raises pydantic's
    ValidationError located at ``<name>.<field>`` (an unregistered name is an unknown key),
    so that the scene's error reads ``effects.<name>.<field>: ...``."""
    fields = {name: (effect_schema(name) | None, None) for name in blocks if name in EFFECT_BLOCKS}
    model = create_model("EffectBlocks", __config__=ConfigDict(extra="forbid", frozen=True), **fields)
    validated = model.model_validate(blocks)
    return {name: getattr(validated, name) for name in blocks}
