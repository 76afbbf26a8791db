"""Registered effects: physics (and memory) a scene can have, each one module, listed in one
place (:data:`EFFECTS`, in pipeline order). What an effect implements, its data and its
YAML block are written out in ``docs/effects.md``; the base class with the protocol's
defaults and the typed accessors is :class:`mysim_jax.core.effect.Effect`.

:func:`mysim_jax.build.build` asks every registered effect to build itself,
:mod:`mysim_jax.sim` runs the updates and stages of those the Scene has. Core types,
builder and step are not edited to add one.
"""

from __future__ import annotations

from dataclasses import dataclass

from mysim_jax.config.effect_blocks import EFFECT_BLOCKS
from mysim_jax.net.drag import LINE_DRAG
from mysim_jax.effects.entanglement import ENTANGLEMENT
from mysim_jax.effects.target import TARGET

# name -> effect, in pipeline order
EFFECTS = {effect.name: effect for effect in (LINE_DRAG, ENTANGLEMENT, TARGET)}


def register(effect) -> None:
    """Register ``effect`` (after those registered before it): in :data:`EFFECTS` and, if it
    has a YAML block (``effect.schema``), its schema in
    :data:`~mysim_jax.config.effect_blocks.EFFECT_BLOCKS`. One line adds an effect; a second
    effect under a name already taken is a ValueError."""
    if EFFECTS.get(effect.name, effect) is not effect:
        raise ValueError(f"an effect named {effect.name!r} is registered already ({EFFECTS[effect.name]!r})")
    EFFECTS[effect.name] = effect
    if getattr(effect, "schema", None) is not None:
        EFFECT_BLOCKS[effect.name] = effect.schema


@dataclass(frozen=True)
class BuildContext:
    """What an effect's ``build`` may need from the assembled scene (host side)."""

    body_names: tuple[str, ...]
    point_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    quadrotor_bodies: tuple[int, ...]   # body index of every quadrotor
    dtype: object                       # jnp.float32 | jnp.float64
    contact: object = None              # the scene's ContactScene (mysim_jax.core.contact_types), or None


def scene_effects(scene):
    """``[(effect, static), ...]`` of the effects this scene has, in pipeline order."""
    return [(EFFECTS[name], static) for name, static in scene.effects]
