"""The base class of a registered effect: the protocol's defaults and typed access to the
effect's parts, so that no code outside the effect spells its name.

An effect's parts sit under its ``name`` in ``Scene.effects`` (static), ``Params.effects``
(traced constants), ``State.effects`` (memory) and, if it has a YAML block, in
``SceneConfig.effects`` (its validated settings). :class:`Effect` reads and replaces them:
``TARGET.params(params)``, ``ENTANGLEMENT.memory(state)``, ``LINE_DRAG.in_scene(scene)``.
The protocol itself (what ``build``, ``update``, ``init`` and ``stages`` do) is written
out once, in ``docs/effects.md``.

Pure Python (no JAX): the accessors only index the ``effects`` fields.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Generic, TypeVar

StaticT = TypeVar("StaticT")
ParamsT = TypeVar("ParamsT")
MemoryT = TypeVar("MemoryT")


class Effect(ABC, Generic[StaticT, ParamsT, MemoryT]):
    """Base of an effect (docs/effects.md): ``name``, the YAML block's ``schema`` (a pydantic
    model; None: no block), ``build`` to implement (abstract), and
    defaults for the rest of the protocol (no update, no memory change, no start state,
    no force stages). Type it with its static part, params and memory:
    ``class _Target(Effect[TargetScene, TargetParams, TargetMemory])``."""

    name: str = ""
    schema: object = None

    # --- the protocol (docs/effects.md) ---------------------------------------------------
    @abstractmethod
    def build(self, config, ctx):
        """The one method every effect implements (docs/effects.md): a subclass without it
        cannot be instantiated."""

    def update(self, scene, params, state):
        return None, self.memory_or_none(state)

    def init(self, scene, params, state):
        return state

    def stages(self, static):
        return ()

    # --- typed access to its parts --------------------------------------------------------
    def block(self, config):
        """Its validated YAML block (an instance of ``schema``) in a SceneConfig, or None."""
        return config.effects.get(self.name)

    def in_scene(self, scene) -> bool:
        """Does the (static) Scene have this effect?"""
        return any(name == self.name for name, _ in scene.effects)

    def static(self, scene) -> StaticT:
        """Its static part in the Scene (KeyError in a scene without it)."""
        return dict(scene.effects)[self.name]

    def params(self, params) -> ParamsT:
        """Its traced constants in the Params."""
        return params.effects[self.name]

    def memory(self, state) -> MemoryT:
        """Its memory in a State (or in anything with an ``effects`` dict of memories, such
        as a Trajectory's stacked rows)."""
        return state.effects[self.name]

    def memory_or_none(self, state) -> MemoryT | None:
        """Its memory, or None where ``state`` carries none of it (a scene without the
        effect, a trajectory saved without memories)."""
        return (getattr(state, "effects", None) or {}).get(self.name)

    def with_params(self, params, value: ParamsT):
        """The Params with this effect's constants replaced by ``value``."""
        return params.replace(effects={**params.effects, self.name: value})

    def with_memory(self, state, value: MemoryT):
        """The State with this effect's memory replaced by ``value``."""
        return state.replace(effects={**state.effects, self.name: value})
