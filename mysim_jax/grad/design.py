"""Tune a capture scene's *design* for its scripted team (``scripts/tune.py --design``):
numeric scene values such as the net's size, the tethers' length or the line's EA, searched
within stated bounds by CMA-ES or random search (:mod:`.search`) on the capture verdict.

**A design** is a vector ``v`` ``(d,)`` of relative changes of ``d`` scene values
(:class:`DesignField`: a dotted key as ``--set`` takes it, and its bounds ``[low, high]``
in the key's units): ``value = nominal * (1 + v)``, ``v = 0`` the scene as configured, so
the box is ``[low / nominal - 1, high / nominal - 1]`` and must hold 0.

**The formation follows the net** (:func:`design_overrides`). A tethered UAV starts where
its tether reaches from its knot; when the net's size or the tethers' length changes, each
tethered UAV's start position moves with its knot (:func:`~mysim_jax.net.config.knot_positions`
of the changed net), and its offset from the knot scales with the tether's length, so the
tethers start as slack as configured and the scripted team flies the same formation, scaled.

**The value** of a design is its miss rate, ``1 - success``, over a **fixed** batch of
episodes (common random numbers: every candidate flies episodes ``0 .. episodes - 1`` of one
evaluation seed, :func:`~mysim_jax.tasks.evaluate.run_episodes`), judged by the
environment's own capture verdict. The episodes' draws (the target's spawn and mass, the
UAVs' masses, the wind) do not depend on the design, so two designs differ on the same
episodes by the design alone. There is no gradient method: a candidate is another scene
(its net's geometry at the start is built from it), so each candidate compiles its own
program, and its value is a count. The budget is counted in team steps as the other
methods' are: a candidate costs ``episodes x max_steps`` (its episodes at their longest).

The training episodes are drawn from ``fold_in(PRNGKey(seed), TRAIN_STREAM)`` (as the team
tuning's), so they are not the episodes a judging evaluation seeded with ``seed`` flies.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Callable

import jax
import numpy as np

from mysim_jax.core.config_base import ConfigError
from mysim_jax.grad.search import SearchResult, check_box, run_search
from mysim_jax.grad.tune import TRAIN_STREAM
from mysim_jax.net.config import knot_positions
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.evaluate import run_episodes, scripted_policy
from mysim_jax.tasks.report import compare

DESIGN_METHODS = ("cmaes", "random")
PLACED_BY = ("net.size", "net.spread", "net.tethers.length")   # these move the tethered UAVs' starts
_FIELD = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*=\s*([^:]+):([^:]+)$")


@dataclass(frozen=True)
class DesignField:
    """One designed scene value: ``key`` (dotted, as ``--set`` takes it) within
    ``[low, high]`` (the key's units)."""

    key: str
    low: float
    high: float

    @classmethod
    def parse(cls, text: str) -> "DesignField":
        """``KEY=LOW:HIGH`` (e.g. ``net.size=1.5:3.5``); ValueError naming the problem."""
        m = _FIELD.match(text)
        if m is None:
            raise ValueError(f"--design {text!r}: expected KEY=LOW:HIGH, e.g. net.size=1.5:3.5")
        key = m.group(1)
        try:
            low, high = float(m.group(2)), float(m.group(3))
        except ValueError:
            raise ValueError(f"--design {text!r}: LOW and HIGH must be numbers") from None
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"--design {text!r}: expected finite LOW < HIGH")
        if key.split(".")[0] in ("level", "levels", "env", "sim"):
            raise ValueError(f"--design {text!r}: {key} is not a design value (the net, its tethers and lines, "
                             "the bodies, the contact)")
        return cls(key, low, high)


def scene_value(config, key: str):
    """The value of dotted ``key`` in a loaded scene ``config`` (list items by index);
    ConfigError when the key is not there."""
    node = config
    for part in key.split("."):
        try:
            node = node[int(part)] if part.isdigit() else getattr(node, part)
        except (AttributeError, IndexError, KeyError, TypeError):
            raise ConfigError(f"--design {key}: the scene has no such value") from None
    return node


def level_keys(config) -> set[str]:
    """The dotted keys the loaded ``config``'s fidelity level sets (empty at ``full``)."""
    level = config.levels.get(config.level) if config.level in config.levels else None
    return set() if level is None else {ov.split("=", 1)[0].strip() for ov in level.set}


def design_overrides(config, values: dict) -> list[str]:
    """``--set`` entries that make ``config`` the design ``values`` (``{key: value}``):
    each value, then every tethered UAV's start position moved with its knot and its offset
    from the knot scaled with the tether's length (module docstring)."""
    out = [f"{key}={value!r}" for key, value in values.items()]
    net = config.net
    if net is None or net.tethers is None or not any(k in values for k in PLACED_BY):
        return out
    changed = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("net.") and "." not in k[4:]}
    new_net = net.model_copy(update=changed)
    length = float(values.get("net.tethers.length", net.tethers.length))
    ratio = length / net.tethers.length
    old_pos, new_pos = knot_positions(net), knot_positions(new_net)
    index = {b.name: k for k, b in enumerate(config.bodies)}
    for uav, (i, j) in zip(net.tethers.uavs, net.tether_knots()):
        start = np.asarray(config.bodies[index[uav]].pos, float)
        moved = new_pos[i, j] + (start - old_pos[i, j]) * ratio
        out.append(f"bodies.{index[uav]}.pos=[{', '.join(repr(float(x)) for x in moved)}]")
    return out


class DesignProblem:
    """The design tuning of a capture scene's scripted team (module docstring).

    ``load(overrides) -> SceneConfig`` loads the scene at the tuning level with extra
    ``--set`` entries; ``fields``: the designed values; ``episodes`` fixed episodes from
    ``seed``, ``batch`` of them side by side. Every input is checked here, before anything
    compiles: ValueError or ConfigError naming the problem."""

    def __init__(self, load: Callable[[list[str]], object], fields: list[DesignField], episodes: int = 64,
                 seed: int = 0, batch: int = 64):
        if not fields:
            raise ValueError("design: no field to tune")
        if len({f.key for f in fields}) != len(fields):
            raise ValueError("design: a key is given twice")
        if not (isinstance(episodes, int) and episodes >= 1 and isinstance(batch, int) and batch >= 1):
            raise ValueError(f"design: episodes {episodes!r} and batch {batch!r} must be ints >= 1")
        self.load, self.fields, self.episodes, self.seed = load, list(fields), episodes, seed
        self.batch = min(batch, episodes)
        self.base = load([])
        if self.base.team is None or self.base.team.policy == "hold":
            raise ConfigError("design: the scene needs a scripted team (team.policy scripted or chase)")
        set_by_level = level_keys(self.base)
        nominal = []
        for f in self.fields:
            if f.key in set_by_level:
                raise ConfigError(f"--design {f.key}: level {self.base.level} sets this value (its own "
                                  "fidelity choice); tune it at a level that does not set it, e.g. --level full")
            value = scene_value(self.base, f.key)
            if isinstance(value, (bool, int)) or not isinstance(value, float):
                raise ConfigError(f"--design {f.key}: the scene's value {value!r} is not a real number (a design "
                                  "value changes continuously)")
            if not f.low <= float(value) <= f.high:
                raise ValueError(f"--design {f.key}={f.low:g}:{f.high:g}: the configured value {float(value):g} "
                                 "must be inside the bounds (the search starts there)")
            if float(value) == 0.0:
                raise ValueError(f"--design {f.key}: the configured value is 0; a relative change needs a "
                                 "nonzero start")
            nominal.append(float(value))
        self.nominal = np.array(nominal)
        lo = np.array([f.low for f in self.fields]) / self.nominal - 1.0
        hi = np.array([f.high for f in self.fields]) / self.nominal - 1.0
        self.lower, self.upper = check_box(np.minimum(lo, hi), np.maximum(lo, hi))
        for f in self.fields:            # each bound alone, the others as configured: the scene must load
            for bound in (f.low, f.high):
                self.config_at_values({**self.values_dict(np.zeros(self.size)), f.key: bound})
        self.max_steps = int(round(self.base.sim.t_end * self.base.env.policy_rate))
        self.evaluated = 0          # designs evaluated (each compiles its own program)
        self._cache: dict[tuple, float] = {}

    @property
    def size(self) -> int:
        return len(self.fields)

    @property
    def names(self) -> list[str]:
        return [f.key for f in self.fields]

    @property
    def steps_per_evaluation(self) -> int:
        return self.episodes * self.max_steps

    @property
    def key(self):
        """The fixed episodes' key (made when first used: after the run has set JAX's precision)."""
        return jax.random.fold_in(jax.random.PRNGKey(self.seed), TRAIN_STREAM)

    def values(self, v) -> np.ndarray:
        """The designed values ``(d,)`` at the relative change ``v`` ``(d,)``."""
        return self.nominal * (1.0 + np.asarray(v, np.float64))

    def values_dict(self, v) -> dict:
        return {f.key: float(x) for f, x in zip(self.fields, self.values(v))}

    def config_at_values(self, values: dict):
        """The scene at the tuning level with the design ``values`` (``{key: value}``)."""
        return self.load(design_overrides(self.base, values))

    def config_at(self, v):
        return self.config_at_values(self.values_dict(v))

    def evaluate(self, V) -> np.ndarray:
        """Miss rate over the fixed episodes of every candidate ``V`` ``(P, d)`` -> ``(P,)``
        (a design evaluated before is not flown again: its episodes are the same)."""
        V = np.asarray(V, np.float64)
        if V.ndim != 2 or V.shape[1] != self.size:
            raise ValueError(f"design: candidates of shape {V.shape}, expected (P, {self.size})")
        out = np.empty(V.shape[0])
        for p, v in enumerate(V):
            if tuple(v) in self._cache:
                out[p] = self._cache[tuple(v)]
                continue
            env, params = make_env(self.config_at(v))
            stats = run_episodes(env, params, scripted_policy(env), self.episodes, self.batch, self.key,
                                 progress=False)
            out[p] = self._cache[tuple(v)] = 1.0 - float(np.mean(stats.success))
            self.evaluated += 1
        return out


def tune_design(problem: DesignProblem, method: str, budget: int, *, batch: int = 8, seed: int = 0,
                sigma0: float = 0.2, population: int | None = None,
                progress: Callable[[int], None] | None = None) -> SearchResult:
    """Minimise ``problem``'s miss rate with ``method`` (``cmaes`` or ``random``) within
    ``budget`` team steps, from the configured design (``v = 0``; random search evaluates
    it in its first batch)."""
    if method not in DESIGN_METHODS:
        raise ValueError(f"design: method {method!r}: expected one of {', '.join(DESIGN_METHODS)} (a candidate "
                         "is another scene and its value a count: there is no gradient to follow)")
    cost = problem.steps_per_evaluation

    def evaluate(V):
        values = problem.evaluate(V)
        if progress is not None:
            progress(len(values) * cost)
        return values

    common = {"lower": problem.lower, "upper": problem.upper, "budget_steps": int(budget), "steps_per_evaluation": cost}
    x0 = np.zeros(problem.size)
    if method == "cmaes":
        return run_search("cmaes", evaluate=evaluate, x0=x0, sigma0=sigma0, population=population, seed=seed,
                          **common)
    return run_search("random", evaluate=evaluate, batch=batch, seed=seed, include=x0, **common)


def judge_design(problem: DesignProblem, v, load_judge: Callable[[list[str]], object], n_episodes: int,
                 batch: int, seed: int, progress: bool = True) -> dict:
    """The design ``v`` and the configured one, each with the scene's scripted team, on
    episodes ``0 .. n_episodes - 1`` of an evaluation seeded with ``seed`` at the judging
    level (``load_judge(overrides)``), by the capture verdict: both success rates with
    Wilson intervals, the paired difference tuned - configured, the per-episode outcomes."""
    key = jax.random.PRNGKey(seed)
    runs = []
    for overrides in (design_overrides(problem.base, problem.values_dict(v)), []):
        env, params = make_env(load_judge(overrides))
        runs.append(run_episodes(env, params, scripted_policy(env), n_episodes, min(batch, n_episodes), key,
                                 progress=progress))
    result = compare(runs[0], runs[1], ("tuned", "configured"))
    result.update(seed=seed, success_per_episode={"tuned": runs[0].success.astype(int).tolist(),
                                                  "configured": runs[1].success.astype(int).tolist()})
    return result
