"""Registered effects: physics (and memory) a scene can have, each one module, listed in one place.

An effect contributes its static part to the Scene (``Scene.effects``), its tunable
constants to the Params (``Params.effects[name]``), its memory to the State
(``State.effects[name]``), an update run once per environment step (its output is held
over the physics sub-steps, like the motor commands) and force stages to the pipeline.
Adding one (target propulsion, an IMU...) is one new module with an object that has

* ``name`` (str);
* ``build(config, ctx) -> (static, params, memory) | None`` — host side, from the
  validated SceneConfig and the :class:`BuildContext`; None when the scene does not have
  the effect (then nothing of it is traced);
* ``update(scene, params, state) -> (held, memory)`` — pure, one environment: what its
  force stages hold over the step, and its new memory;
* ``stages(static) -> ((stage_name, fn), ...)`` with
  ``fn(scene, params, phys, nodes, held) -> Loads`` (:mod:`mysim_jax.dynamics.forces`);
* ``init(scene, params, state) -> state`` — the start state the effect asks for (e.g. the
  target's seeded spawn), applied by the builder in registry order;

and one entry in :data:`EFFECTS` below. :func:`mysim_jax.build.build` asks every
registered effect to build itself, :mod:`mysim_jax.sim` runs the updates and stages of
those the Scene has. Core types, builder and step are not edited.
"""

from __future__ import annotations

from dataclasses import dataclass

from mysim_jax.contact.broad_phase import BROAD_PHASE
from mysim_jax.net.drag import LINE_DRAG
from mysim_jax.effects.entanglement import ENTANGLEMENT
from mysim_jax.effects.target import TARGET

# name -> effect, in pipeline order
EFFECTS = {effect.name: effect for effect in (BROAD_PHASE, LINE_DRAG, ENTANGLEMENT, TARGET)}


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
