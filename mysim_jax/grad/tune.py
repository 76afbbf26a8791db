"""Tune a capture scene's scripted team on the smooth capture objective
(``scripts/tune.py``; the minimisers are :mod:`.search`).

A :class:`TuningProblem` is one environment's scripted team with the fields a user can set
in the scene's ``team:`` block (:class:`~mysim_jax.config.capture.TeamConfig`; the
team's other float fields stay as built) as a vector ``v`` ``(d,)`` of relative changes
(:mod:`.team`: ``field = nominal + scale * v``, ``v = 0`` the configured team), inside a
box: ``[lower, upper]`` per field, narrowed so that every point of it passes the team
config's own checks (a field the config requires ``> 0`` or ``>= 0`` stays so, and the
chase's ``close`` stays below its ``climb_radius``: their ranges are split halfway between
the two nominal values when they would overlap).

The value of ``v`` is the objective ``J`` [m] of :mod:`.objective` over a horizon of
``horizon`` policy steps from the episode's reset (default: the whole episode), closed
loop (the team flies with ``v``), averaged over a **fixed** batch of training episodes:
every candidate flies the same episodes with the same random draws (common random
numbers), so two candidates' values differ only by the team. The training episodes are
drawn from ``fold_in(PRNGKey(seed), TRAIN_STREAM)``, so they are not the episodes an
evaluation seeded with ``seed`` flies (:mod:`mysim_jax.tasks.evaluate` numbers those from
``PRNGKey(seed)``).

* :meth:`TuningProblem.evaluate` ``(P, d) -> (P,)``: all candidates x episodes in one
  batched closed-loop rollout (:meth:`~.engine.GradientEngine.rollouts`);
* :meth:`TuningProblem.value_and_grad` ``(d,) -> (value, (d,))``: the forward rollout
  with its states, then the engine's reverse pass (closed loop, optionally truncated to
  ``truncate`` policy steps), averaged over the episodes;
* ``steps_per_evaluation`` = episodes x horizon: the team steps one evaluation costs
  (:mod:`.search`'s budget unit).

:func:`tune` runs one of :data:`~.search.METHODS` at a budget of team steps;
:func:`tuned_team` gives the team with the tuned fields as plain floats and
:func:`team_block` the scene's ``team:`` values to paste; :func:`judge` flies the tuned
team and the configured one on the same fresh episodes with the real capture verdict.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.config.capture import TeamConfig
from mysim_jax.grad.engine import GradientEngine, stack_start
from mysim_jax.grad.objective import ObjectiveWeights
from mysim_jax.grad.rollout import horizon_values
from mysim_jax.grad.search import SearchResult, check_box, run_search
from mysim_jax.grad.team import team_actions
from mysim_jax.tasks.evaluate import run_two_teams, scripted_policy
from mysim_jax.tasks.report import compare

TRAIN_STREAM = 0x7E57          # folded into the seed: the training episodes' stream
ORDERED = (("close", "climb_radius"),)     # (a, b): the team config requires a < b


def config_limits(name: str) -> tuple[float | None, bool]:
    """``(limit, strict)``: the lower limit :class:`TeamConfig` puts on field ``name``
    (``gt``/``ge`` of its annotation; ``(None, False)`` without one)."""
    for meta in TeamConfig.model_fields[name].metadata:
        if getattr(meta, "gt", None) is not None:
            return float(meta.gt), True
        if getattr(meta, "ge", None) is not None:
            return float(meta.ge), False
    return None, False


def tunable_names(team_params) -> tuple[str, ...]:
    """The team's parameters (:class:`~.team.TeamParameters`) that the scene's ``team:``
    block sets (the others stay as built)."""
    names = tuple(n for n in team_params.names if n in TeamConfig.model_fields)
    if not names:
        raise ValueError("tuning: the team has no field that its config's team: block sets")
    return names


def config_box(team_params, names, lower: float, upper: float, margin: float = 0.02):
    """``(lower, upper)`` ``(d,)`` in relative units for ``names``: ``[lower, upper]``
    per field, narrowed to the team config's checks (module docstring; a strict limit
    kept ``margin`` of the scale away)."""
    lo, hi = np.full(len(names), float(lower)), np.full(len(names), float(upper))
    idx = {n: team_params.names.index(n) for n in names}
    nom = {n: team_params.nominal[idx[n]] for n in names}
    scale = {n: team_params.scale[idx[n]] for n in names}
    for j, n in enumerate(names):
        limit, strict = config_limits(n)
        if limit is not None:
            lo[j] = max(lo[j], (limit - nom[n]) / scale[n] + (margin if strict else 0.0))
    for a, b in ORDERED:
        if a not in idx or b not in idx:
            continue
        ja, jb = names.index(a), names.index(b)
        if nom[a] + scale[a] * hi[ja] < nom[b] + scale[b] * lo[jb]:
            continue
        mid = 0.5 * (nom[a] + nom[b])
        hi[ja] = min(hi[ja], (mid - nom[a]) / scale[a] - margin)
        lo[jb] = max(lo[jb], (mid - nom[b]) / scale[b] + margin)
    return check_box(np.minimum(lo, 0.0), np.maximum(hi, 0.0))     # the configured team stays inside


class TuningProblem:
    """The tuning of ``env``'s scripted team (module docstring).

    ``episodes``: the fixed batch of training episodes; ``horizon``: policy steps from the
    reset (None: the episode's ``max_steps``); ``box``: the relative bounds per field;
    ``truncate``: the reverse pass's truncation in policy steps (None: none)."""

    def __init__(self, env, params, weights: ObjectiveWeights = ObjectiveWeights(), episodes: int = 4,
                 horizon: int | None = None, seed: int = 0, box: tuple[float, float] = (-0.5, 0.5),
                 truncate: int | None = None):
        horizon = env.max_steps if horizon is None else horizon
        if not (isinstance(episodes, int) and episodes >= 1):
            raise ValueError(f"tuning: episodes {episodes!r}, expected an int >= 1")
        if not (isinstance(horizon, int) and 1 <= horizon <= env.max_steps):
            raise ValueError(f"tuning: horizon {horizon!r} policy steps, expected 1..{env.max_steps} (the episode)")
        if truncate is not None and not (isinstance(truncate, int) and truncate >= 1):
            raise ValueError(f"tuning: truncate {truncate!r}, expected None or an int >= 1")
        self.engine = GradientEngine(env, params, weights)
        self.episodes, self.horizon, self.seed, self.truncate = episodes, horizon, seed, truncate
        full = self.engine.problem.team
        self.names = tunable_names(full)
        self.index = np.array([full.names.index(n) for n in self.names])
        self.lower, self.upper = config_box(full, self.names, *box)
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), TRAIN_STREAM), episodes)
        split = jax.vmap(jax.random.split)(keys)
        self.run_keys = split[:, 1]
        self.starts = jax.jit(jax.vmap(lambda k: env.reset(k, params)[1]))(split[:, 0])
        self.dtype = self.starts.sim.phys.body_pos.dtype
        self._sizes = set()           # the candidate counts evaluate has compiled for

    @property
    def env(self):
        return self.engine.env

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def steps_per_evaluation(self) -> int:
        return self.episodes * self.horizon

    @property
    def nominal(self) -> np.ndarray:
        """The tuned fields' configured values ``(d,)``."""
        return np.array([self.engine.problem.team.nominal[i] for i in self.index])

    def values(self, v) -> np.ndarray:
        """The tuned fields' values ``(d,)`` at the relative change ``v`` ``(d,)``."""
        scale = np.array([self.engine.problem.team.scale[i] for i in self.index])
        return self.nominal + scale * np.asarray(v, np.float64)

    def full_u(self, V):
        """``V`` ``(..., d)`` in the engine's parameter vector ``(..., n_params)`` (the
        fields not tuned at 0: as built)."""
        V = jnp.asarray(V, self.dtype)
        out = jnp.zeros((*V.shape[:-1], self.engine.problem.team.size), self.dtype)
        return out.at[..., self.index].set(V)

    def _check(self, V, ndim):
        V = np.asarray(V, np.float64)
        if V.ndim != ndim or V.shape[-1] != self.size:
            raise ValueError(f"tuning: candidates of shape {V.shape}, expected {'(P, ' if ndim == 2 else '('}"
                             f"{self.size}) for the fields {', '.join(self.names)}")
        return V

    def _tiled(self, P):
        """The starts and run keys ``(P * episodes, ...)``: candidate-major."""
        states = jax.tree.map(lambda a: jnp.tile(a, (P,) + (1,) * (a.ndim - 1)), self.starts)
        return states, jnp.tile(self.run_keys, (P, 1))

    def evaluate(self, V) -> np.ndarray:
        """Mean ``J`` [m] over the episodes of every candidate ``V`` ``(P, d)`` -> ``(P,)``.
        Fewer candidates than an earlier call are padded to that call's number (one
        compiled program serves both: a search's last, smaller batch compiles nothing)."""
        V = self._check(V, 2)
        larger = [p for p in self._sizes if p > V.shape[0]]
        if larger:
            pad = np.zeros((min(larger) - V.shape[0], self.size))
            return self.evaluate(np.concatenate([V, pad]))[:V.shape[0]]
        self._sizes.add(V.shape[0])
        P, B, n = V.shape[0], self.episodes, self.horizon
        states, keys = self._tiled(P)
        u = jnp.repeat(self.full_u(V), B, axis=0)
        actions = jnp.zeros((P * B, n, *self.env.action_shape), self.dtype)
        rows, _, _ = self.engine.rollouts(states, keys, jnp.ones(P * B, bool), u, actions, n)
        values = jax.vmap(lambda r: horizon_values(r, [n])[0])(rows)
        return np.asarray(values, np.float64).reshape(P, B).mean(axis=1)

    def value_and_grad(self, v):
        """``(value, grad)``: the mean ``J`` [m] at ``v`` ``(d,)`` and its gradient ``(d,)``
        by the reverse pass (closed loop, truncated to ``truncate`` steps if set)."""
        v = self._check(v, 1)
        B, n = self.episodes, self.horizon
        u = jnp.repeat(self.full_u(v[None]), B, axis=0)
        actions = jnp.zeros((B, n, *self.env.action_shape), self.dtype)
        rows, flown, states = self.engine.rollouts(self.starts, self.run_keys, jnp.ones(B, bool), u, actions, n,
                                                   keep_states=True)
        value = jnp.mean(jax.vmap(lambda r: horizon_values(r, [n])[0])(rows))
        window = stack_start(self.starts, states)
        g = self.engine.gradient(window, self.run_keys, u, flown, n, closed_loop=True, truncate=self.truncate)
        return float(value), np.asarray(jnp.mean(g, axis=0)[self.index], np.float64)


def tune(problem: TuningProblem, method: str, budget: int, *, batch: int = 8, seed: int = 0, sigma0: float = 0.2,
         population: int | None = None, learning_rate: float = 0.05, clip_norm: float | None = 1.0,
         progress: Callable[[int], None] | None = None) -> SearchResult:
    """Minimise ``problem``'s value with ``method`` (``grad``, ``cmaes``, ``random``) at a
    budget of ``budget`` team steps from the configured team (``v = 0``; random search
    evaluates it in its first batch). ``progress(team_steps)`` is called after every
    evaluation call with the team steps it spent."""
    cost = problem.steps_per_evaluation
    lower, upper, x0 = problem.lower, problem.upper, np.zeros(problem.size)

    def evaluate(V):
        values = problem.evaluate(V)
        if progress is not None:
            progress(len(values) * cost)
        return values

    def value_and_grad(v):
        out = problem.value_and_grad(np.asarray(v, np.float64))
        if progress is not None:
            progress(cost)
        return out

    common = {"lower": lower, "upper": upper, "budget_steps": int(budget), "steps_per_evaluation": cost}
    if method == "grad":
        return run_search("grad", value_and_grad=value_and_grad, x0=x0, learning_rate=learning_rate,
                          clip_norm=clip_norm, **common)
    if method == "cmaes":
        return run_search("cmaes", evaluate=evaluate, x0=x0, sigma0=sigma0, population=population, seed=seed,
                          **common)
    return run_search(method, evaluate=evaluate, batch=batch, seed=seed, include=x0, **common)


def tuned_fields(problem: TuningProblem, v) -> dict:
    """``{field: value}`` of the tuned fields at ``v`` ``(d,)`` as plain floats."""
    return {n: float(x) for n, x in zip(problem.names, problem.values(v))}


def tuned_team(problem: TuningProblem, v, team=None):
    """``team`` (default the problem's scripted team; e.g. the same scene's team at another
    level) with the tuned fields set from ``v`` ``(d,)`` as plain floats."""
    team = problem.env.scripted if team is None else team
    return dataclasses.replace(team, **tuned_fields(problem, v))


def team_block(problem: TuningProblem, v, policy: str, digits: int = 4) -> dict:
    """The scene's ``team:`` values for ``v`` (``policy`` and every tuned field, rounded
    to ``digits`` significant digits), checked by :class:`TeamConfig`: paste them into
    the scene's ``team:`` block."""
    def rounded(x):
        return 0.0 if x == 0.0 else round(x, digits - 1 - int(math.floor(math.log10(abs(x)))))

    block = {"policy": policy, **{n: rounded(x) for n, x in tuned_fields(problem, v).items()}}
    TeamConfig(**block)
    return block


def team_policy_of(env, team):
    """``policy(key, obs, state, params)`` flying ``team`` in ``env`` (the environment's
    scripted actions with ``team`` in place of its own)."""
    def policy(key, obs, state, params):
        return team_actions(env, team, state, params)
    return policy


def judge(problem: TuningProblem, v, env, params, n_episodes: int, batch: int, seed: int,
          progress: bool = True) -> dict:
    """The tuned team (``v``) and ``env``'s configured team on episodes ``0 ..
    n_episodes - 1`` of an evaluation seeded with ``seed`` (``env``: the same scene, at
    the judging level), the real capture verdict: both success rates with Wilson
    intervals and the paired difference tuned - configured
    (:func:`mysim_jax.tasks.report.compare`), and the per-episode outcomes."""
    tuned = tuned_team(problem, v, env.scripted)
    a, b = run_two_teams(env, params, team_policy_of(env, tuned), scripted_policy(env), n_episodes,
                         min(batch, n_episodes), jax.random.PRNGKey(seed), progress=progress)
    result = compare(a, b, ("tuned", "configured"))
    result.update(seed=seed, success_per_episode={"tuned": a.success.astype(int).tolist(),
                                                  "configured": b.success.astype(int).tolist()})
    return result
