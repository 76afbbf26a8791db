"""The scripted team's continuous fields as a parameter vector that gradients flow to.

The scripted teams (:mod:`mysim_jax.tasks.scripted`) are frozen, hashable dataclasses
with Python floats: static for jit. :class:`TeamParameters` lists a team's tunable
fields (every float field but the scene's own quantities, :data:`NOT_TUNED`) and maps a
vector ``u`` ``(n_params,)`` of **relative** changes to a copy of the team whose fields
are traced values, ``field = nominal + scale * u`` (``scale`` = ``max(|nominal|,
min_scale)``): ``u = 0`` is the team as configured, and ``u_i = 0.01`` changes field
``i`` by about 1 %. The copy is only ever called inside a traced function, never hashed;
the team itself is unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax.numpy as jnp

# float fields of a team that describe the scene rather than the team's choices
NOT_TUNED = ("net_drop", "drag_per_mass")


@dataclass(frozen=True)
class TeamParameters:
    """A team's tunable fields, their nominal values and scales (module docstring)."""

    names: tuple[str, ...]
    nominal: tuple[float, ...]
    scale: tuple[float, ...]

    @property
    def size(self) -> int:
        return len(self.names)

    def values(self, u):
        """The fields' values ``(n_params,)`` at the relative change ``u``."""
        return jnp.asarray(self.nominal, u.dtype) + jnp.asarray(self.scale, u.dtype) * u

    def team(self, team, u):
        """A copy of ``team`` with its tunable fields set from ``u`` (traced values)."""
        values = self.values(u)
        return dataclasses.replace(team, **{n: values[i] for i, n in enumerate(self.names)})


def team_parameters(team, min_scale: float = 0.1) -> TeamParameters:
    """The tunable fields of a scripted ``team`` (a dataclass; ValueError for a team with
    none, e.g. :class:`~mysim_jax.tasks.scripted.HoldTeam`)."""
    if team is None or not dataclasses.is_dataclass(team):
        raise ValueError(f"team parameters: {type(team).__name__} is not a scripted team dataclass")
    names = tuple(f.name for f in dataclasses.fields(team)
                  if isinstance(getattr(team, f.name), float) and f.name not in NOT_TUNED)
    if not names:
        raise ValueError(f"team parameters: {type(team).__name__} has no continuous fields to tune")
    nominal = tuple(float(getattr(team, n)) for n in names)
    return TeamParameters(names=names, nominal=nominal, scale=tuple(max(abs(v), min_scale) for v in nominal))


def team_actions(env, team, state, params):
    """The actions ``(n_agents, 3)`` of ``team`` in the environment's action space (the
    environment's own :meth:`~mysim_jax.tasks.capture.env.CaptureEnv.scripted_actions`
    with ``team`` in place of its scripted team)."""
    return dataclasses.replace(env, scripted=team).scripted_actions(state, params)
