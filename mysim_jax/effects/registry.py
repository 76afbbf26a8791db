"""Registered effects at run time: physics (and memory) a scene can have, each one module
and one entry of the registry (:data:`EFFECTS`, in pipeline order; the table itself is
:data:`mysim_jax.config.effect_blocks.EFFECTS`, which the config layer reads to validate
the effects' YAML blocks without importing them). What an effect implements, its data and
its YAML block are written out in ``docs/effects.md``; the base class with the protocol's
defaults and the typed accessors is :class:`mysim_jax.core.effect.Effect`.

:func:`mysim_jax.build.build` asks every registered effect to build itself,
:mod:`mysim_jax.sim` runs the updates and stages of those the Scene has. Core types,
builder and step are not edited to add one.
"""

from __future__ import annotations

from dataclasses import dataclass

from mysim_jax.config.effect_blocks import EFFECTS, registered_effect

__all__ = ["EFFECTS", "BuildContext", "register", "registered_effect", "registered_effects", "scene_effects"]


def register(effect) -> None:
    """Register ``effect`` (after those registered before it) in :data:`EFFECTS`: the one
    line that adds an effect outside the library, its YAML block (``effect.schema``)
    included. A second effect under a name already taken is a ValueError."""
    if effect.name in EFFECTS and registered_effect(effect.name) is not effect:
        raise ValueError(f"an effect named {effect.name!r} is registered already ({EFFECTS[effect.name]!r})")
    EFFECTS[effect.name] = effect


def registered_effects() -> list:
    """Every registered effect, in pipeline order (the library's imported on first use)."""
    return [registered_effect(name) for name in list(EFFECTS)]


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
    return [(registered_effect(name), static) for name, static in scene.effects]
