"""The episode runner: every rollout of a policy on an environment outside training.

    (obs, state, aux), rows = rollout(env, params, policy, obs, state, xs, record=record)
    (obs, state), rows = run_batch(env, params, policy, keys, length, record=record)

A **policy step** is ``actions = policy(k_act, obs, state, params)`` and then
``env.step(k_step, state, actions, params)`` (which resets an ended episode) or, with
``auto_reset=False``, ``env.step_env`` (which does not) (:func:`policy_step`).
:func:`rollout` runs policy steps of one environment as one ``lax.scan``; it is pure (the
caller jits it and batches it, with the library's batch-last
:func:`mysim_jax.core.batching.vmap`). :func:`run_batch` resets a batch of environments
from their keys and runs them side by side, jitted. What differs between the users is
given as arguments:

* ``keys(x, aux) -> (k_act, k_step)``: the policy's and the environment's key of a step,
  from the step's scanned input ``x`` (an element of ``xs``) and the caller's carry
  ``aux``. :func:`split_keys` (the default: ``xs`` holds a key per step, split in two),
  :func:`shared_key` (the step's key given to both, for policies that draw nothing), or
  :func:`numbered_keys` (step ``t`` of a numbered episode, ``xs`` the step numbers:
  :func:`episode_keys`).
* ``record(step, aux) -> row``: what to keep of a :class:`PolicyStep`; the rows come back
  stacked along a leading step axis (``record`` None: nothing, only the final carry).
  :func:`first_done` reduces the rows to the outcome of the first episode.
* ``update(step, aux) -> (obs, state, aux)``: where the next step starts (default: what
  ``env.step`` returned, ``aux`` unchanged). Both hooks see the ``aux`` the step was taken
  with. Evaluation starts a slot's next episode here.
* ``auto_reset``: step with ``env.step``, which resets an ended episode (training's
  behaviour), or with ``env.step_env``, which keeps its terminal state (one recorded
  episode, evaluation's slots).

The users: :class:`~mysim_jax.tasks.evaluate.Evaluator` (numbered episodes in slots, a
row per step with the outcome of an episode ending there), :func:`~mysim_jax.tasks.episode.episode_rollout`
(one numbered episode, every step's row), behaviour cloning's demonstrations
(:func:`mysim_jax.mappo.bc.collect`: a key per step, the scripted team plus noise, auto-reset),
the reach task's evaluation (:func:`mysim_jax.mappo.run.evaluate_builtin`: :func:`run_batch`
and :func:`first_done`) and the bench's environment timings (the final states alone).
The trainer's rollout (:mod:`mysim_jax.mappo.trainer`) is its own: it also carries the
observation statistics, the critic's values and the actions' log-probabilities PPO needs.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from mysim_jax.core import batching


class PolicyStep(NamedTuple):
    """One policy step of one environment, as ``record`` and ``update`` see it."""

    obs: Any             # (n_agents, obs_size) the observation the policy acted on
    state: Any           # the environment's state before the step
    actions: Any         # (n_agents, action) as the policy gave them
    reward: Any          # (n_agents,)
    terminated: Any      # () bool
    truncated: Any       # () bool
    info: dict           # env.step's info
    next_obs: Any        # (n_agents, obs_size) returned by env.step (a reset one after an
    next_state: Any      # auto-reset), and the state returned with it


def episode_key(key, index):
    """The key that episode ``index`` of an evaluation seeded with ``key`` is drawn from."""
    return jax.random.fold_in(key, index)


def episode_keys(key, index, step):
    """``(reset_key, policy_key, env_key)`` of step ``step`` of episode ``index``: the reset
    from the first half of ``split(episode_key(key, index))``, step ``step`` from
    ``fold_in(second half, step)`` split in two (:mod:`mysim_jax.tasks.evaluate`)."""
    k_reset, k_run = jax.random.split(episode_key(key, index))
    k_act, k_step = jax.random.split(jax.random.fold_in(k_run, step))
    return k_reset, k_act, k_step


def split_keys(x, aux=None):
    """``(policy key, env key)``: the step's key ``x`` split in two."""
    k_act, k_step = jax.random.split(x)
    return k_act, k_step


def shared_key(x, aux=None):
    """``(x, x)``: the step's key to both, for a policy that draws nothing (scripted,
    deterministic); the environment's draws are then those of ``x`` alone."""
    return x, x


def numbered_keys(key, index) -> Callable:
    """``keys`` of episode ``index`` of an evaluation seeded with ``key``: with ``xs`` the
    step numbers ``t``, step ``t``'s keys of :func:`episode_keys`."""
    def keys(t, aux=None):
        _, k_act, k_step = episode_keys(key, index, t)
        return k_act, k_step
    return keys


def policy_step(env, params, policy, obs, state, k_act, k_step, auto_reset: bool = True) -> PolicyStep:
    """``policy(k_act, obs, state, params)``'s actions, then ``env.step`` with them
    (``env.step_env`` when not ``auto_reset``)."""
    actions = policy(k_act, obs, state, params)
    step = env.step if auto_reset else env.step_env
    next_obs, next_state, reward, terminated, truncated, info = step(k_step, state, actions, params)
    return PolicyStep(obs, state, actions, reward, terminated, truncated, info, next_obs, next_state)


def rollout(env, params, policy, obs, state, xs=None, *, length: int | None = None, keys: Callable = split_keys,
            record: Callable | None = None, update: Callable | None = None, aux=None, auto_reset: bool = True):
    """Policy steps of one environment from ``(obs, state)`` as one ``lax.scan`` over ``xs``
    (or ``length`` steps with ``xs`` None), with the hooks of the module docstring. Pure.

    Returns ``((obs, state, aux), rows)``: where the last step left the carry, and
    ``record``'s rows stacked along a leading step axis (None without ``record``)."""
    def body(carry, x):
        obs, state, aux = carry
        k_act, k_step = keys(x, aux)
        step = policy_step(env, params, policy, obs, state, k_act, k_step, auto_reset)
        row = None if record is None else record(step, aux)
        carry = (step.next_obs, step.next_state, aux) if update is None else update(step, aux)
        return carry, row

    return jax.lax.scan(body, (obs, state, aux), xs, length=length)


def run_batch(env, params, policy, keys, length: int, *, step_keys: Callable = split_keys,
              record: Callable | None = None, auto_reset: bool = True, vmap: Callable | None = None):
    """``len(keys)`` environments side by side for ``length`` policy steps, jitted:
    environment ``i`` resets from the first half of ``split(keys[i])`` and steps over
    ``split(second half, length)`` (``step_keys`` makes each step's two keys of those).
    ``vmap``: how the batch is mapped (default the library's batch-last
    :func:`mysim_jax.core.batching.vmap`, in blocks sized from the state).

    Returns ``((obs, state), rows)`` with a leading batch axis (``rows``: ``(batch,
    length, ...)``, None without ``record``)."""
    if length < 1:
        raise ValueError(f"run_batch: length must be at least 1, got {length}")

    def one(key):
        k_reset, k_run = jax.random.split(key)
        obs, state = env.reset(k_reset, params)
        (obs, state, _), rows = rollout(env, params, policy, obs, state, jax.random.split(k_run, length),
                                        keys=step_keys, record=record, auto_reset=auto_reset)
        return (obs, state), rows

    if vmap is None:
        one_state = jax.eval_shape(lambda: env.reset(jax.random.PRNGKey(0), params)[1])
        vmap = lambda f: batching.vmap(f, chunk=batching.chunk_for(one_state))     # noqa: E731
    return jax.jit(vmap(one))(keys)


def first_done(rows: dict) -> tuple[Any, Any]:
    """``(row, ended)``: the row of the first step whose ``rows["done"]`` is set (each leaf
    of ``rows`` indexed there; ``rows`` of one environment, leading step axis) and whether
    any step ended an episode (if none did, ``row`` is the first step's). Pure."""
    done = rows["done"]
    first = jnp.argmax(done)
    return jax.tree.map(lambda a: a[first], rows), jnp.any(done)
