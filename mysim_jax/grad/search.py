"""Three ways to minimise an objective of a parameter vector at one simulation budget:
gradient descent (optax), CMA-ES (the ``cmaes`` package) and random search.

Every method sees the objective the same way, as a batch of candidates at a time:

* ``evaluate(U) -> values``: ``U`` ``(P, d)`` candidates, ``values`` ``(P,)`` (lower is
  better), e.g. the capture objective's mean over a fixed batch of episodes for each
  candidate, all ``P`` in one vmapped program;
* ``value_and_grad(u) -> (value, grad)`` (gradient descent only): one candidate ``(d,)``.

**The budget** is counted in simulated team steps (policy steps of the whole team), so
that the methods compare at equal simulation: a candidate's evaluation costs
``steps_per_evaluation`` (episodes x horizon steps), and a gradient step costs the same
as one evaluation (its forward rollout; the reverse pass is not counted as steps, its time
is in the wall time each method reports). A method stops before the step that would go over the budget.

The search space is the box ``[lower, upper]`` (``(d,)`` each): CMA-ES keeps its samples
inside it, random search draws uniformly from it, and gradient descent projects its
iterates onto it. All three record the best value seen after each step
(:class:`SearchResult`), which is what a user plots against the budget.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import jax.numpy as jnp
import numpy as np
import optax
from cmaes import CMA

METHODS = ("grad", "cmaes", "random")


@dataclass
class SearchResult:
    """The outcome of one search.

    ``best_u`` ``(d,)`` the best candidate evaluated and ``best_value`` its value;
    ``history``: one row per step (a gradient step, a CMA-ES generation, a random batch)
    with ``team_steps`` spent so far, ``evaluations`` so far, ``value`` (the step's best
    or, for gradient descent, the iterate's value), ``best`` (best so far) and ``wall_s``."""

    method: str
    best_u: np.ndarray
    best_value: float
    history: list[dict] = field(default_factory=list)

    @property
    def team_steps(self) -> int:
        return self.history[-1]["team_steps"] if self.history else 0


def check_box(lower, upper) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` as float arrays ``(d,)``; ValueError unless ``lower < upper``
    element-wise and both are finite and of one shape."""
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    if lower.ndim != 1 or lower.shape != upper.shape or lower.size == 0:
        raise ValueError(f"search box: lower {lower.shape} and upper {upper.shape} must be the same (d,) shape")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower < upper)):
        raise ValueError("search box: every bound must be finite with lower < upper")
    return lower, upper


def evaluations_in(budget_steps: int, steps_per_evaluation: int) -> int:
    """How many evaluations ``budget_steps`` team steps buy (ValueError when not one)."""
    if not (isinstance(steps_per_evaluation, int) and steps_per_evaluation >= 1):
        raise ValueError(f"steps per evaluation: {steps_per_evaluation!r}, expected an int >= 1")
    n = int(budget_steps) // steps_per_evaluation
    if n < 1:
        raise ValueError(f"budget {budget_steps} team steps is less than one evaluation "
                         f"({steps_per_evaluation} team steps): raise the budget")
    return n


def _row(evals: int, cost: int, value: float, best: float, t0: float) -> dict:
    return {"evaluations": evals, "team_steps": evals * cost, "value": float(value), "best": float(best),
            "wall_s": round(time.perf_counter() - t0, 3)}


def _values(evaluate: Callable, U: np.ndarray) -> np.ndarray:
    values = np.asarray(evaluate(U), dtype=np.float64).reshape(-1)
    if values.shape != (U.shape[0],):
        raise ValueError(f"evaluate returned {values.shape} values for {U.shape[0]} candidates")
    return np.where(np.isfinite(values), values, np.inf)      # a non-finite run counts as the worst


def random_search(evaluate: Callable, lower, upper, budget_steps: int, steps_per_evaluation: int,
                  batch: int = 16, seed: int = 0, include: np.ndarray | None = None) -> SearchResult:
    """Uniform draws from the box, ``batch`` at a time, until the budget is spent;
    ``include`` (``(d,)``, e.g. the nominal point) is evaluated in the first batch."""
    lower, upper = check_box(lower, upper)
    n_total = evaluations_in(budget_steps, steps_per_evaluation)
    rng, t0 = np.random.default_rng(seed), time.perf_counter()
    result = SearchResult("random", np.zeros_like(lower), np.inf)
    done = 0
    while done < n_total:
        n = min(batch, n_total - done)
        U = rng.uniform(lower, upper, size=(n, lower.size))
        if done == 0 and include is not None:
            U[0] = np.clip(include, lower, upper)
        values = _values(evaluate, U)
        done += n
        i = int(np.argmin(values))
        if values[i] < result.best_value:
            result.best_u, result.best_value = U[i].copy(), float(values[i])
        result.history.append(_row(done, steps_per_evaluation, values[i], result.best_value, t0))
    return result


def cma_es(evaluate: Callable, x0, sigma0: float, lower, upper, budget_steps: int, steps_per_evaluation: int,
           population: int | None = None, seed: int = 0) -> SearchResult:
    """CMA-ES (``cmaes.CMA``: ask a generation, evaluate it in one call, tell) from mean
    ``x0`` with step size ``sigma0``, its samples kept in the box, until the budget cannot
    pay for another whole generation."""
    lower, upper = check_box(lower, upper)
    if not sigma0 > 0.0:
        raise ValueError(f"cma_es: sigma0 {sigma0!r}, expected > 0")
    n_total = evaluations_in(budget_steps, steps_per_evaluation)
    opt = CMA(mean=np.clip(np.asarray(x0, np.float64), lower, upper), sigma=float(sigma0),
              bounds=np.stack([lower, upper], axis=1), seed=seed, population_size=population)
    if n_total < opt.population_size:
        raise ValueError(f"cma_es: the budget buys {n_total} evaluations, fewer than one generation of "
                         f"{opt.population_size}: raise the budget or lower the population")
    t0 = time.perf_counter()
    result = SearchResult("cmaes", np.asarray(x0, np.float64), np.inf)
    done = 0
    while done + opt.population_size <= n_total:
        U = np.stack([opt.ask() for _ in range(opt.population_size)])
        values = _values(evaluate, U)
        done += U.shape[0]
        # CMA-ES ranks its samples: a non-finite value is told as a large finite one
        finite_max = np.max(values[np.isfinite(values)]) if np.any(np.isfinite(values)) else 0.0
        told = np.where(np.isfinite(values), values, finite_max + 1e6)
        opt.tell([(U[k], float(told[k])) for k in range(U.shape[0])])
        i = int(np.argmin(values))
        if values[i] < result.best_value:
            result.best_u, result.best_value = U[i].copy(), float(values[i])
        result.history.append(_row(done, steps_per_evaluation, values[i], result.best_value, t0))
    return result


def gradient_descent(value_and_grad: Callable, x0, lower, upper, budget_steps: int, steps_per_evaluation: int,
                     optimizer=None, learning_rate: float = 0.05, clip_norm: float | None = 1.0) -> SearchResult:
    """Projected first-order descent with an optax ``optimizer`` (default Adam at
    ``learning_rate``, the gradient clipped to ``clip_norm`` in norm first): one step per
    ``steps_per_evaluation`` of budget; the best iterate seen is the result."""
    lower, upper = check_box(lower, upper)
    n_total = evaluations_in(budget_steps, steps_per_evaluation)
    if optimizer is None:
        chain = [optax.clip_by_global_norm(clip_norm)] if clip_norm is not None else []
        optimizer = optax.chain(*chain, optax.adam(learning_rate))
    u = jnp.asarray(np.clip(np.asarray(x0, np.float64), lower, upper), jnp.float32)
    state, t0 = optimizer.init(u), time.perf_counter()
    result = SearchResult("grad", np.asarray(u, np.float64), np.inf)
    for k in range(n_total):
        value, grad = value_and_grad(u)
        value = float(value)
        if not np.isfinite(value):
            value = np.inf
        if value < result.best_value:
            result.best_u, result.best_value = np.asarray(u, np.float64), value
        result.history.append(_row(k + 1, steps_per_evaluation, value, result.best_value, t0))
        grad = jnp.where(jnp.isfinite(grad), grad, 0.0)
        updates, state = optimizer.update(grad, state, u)
        u = jnp.clip(optax.apply_updates(u, updates), lower, upper)
    return result


def run_search(method: str, **kwargs) -> SearchResult:
    """Dispatch on ``method`` (:data:`METHODS`) with that method's keyword arguments."""
    fns = {"grad": gradient_descent, "cmaes": cma_es, "random": random_search}
    if method not in fns:
        raise ValueError(f"search method {method!r}: expected one of {', '.join(METHODS)}")
    return fns[method](**kwargs)
