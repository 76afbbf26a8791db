"""The MAPPO networks and the deterministic policy a trained actor flies.

The actor maps one agent's observation to the mean of a diagonal Gaussian over its action
(log standard deviations are free parameters); the critic maps the global state with an
agent's one-hot id to that agent's value (:mod:`mysim_jax.mappo.trainer` trains both).
:func:`deterministic_policy` is the actor's mean, clipped to the action bounds: what a
saved policy does when it is evaluated.

The weight matrices start orthogonal (:func:`orthogonal`). Under ``jax.vmap`` (seeds
trained in one program) their QR factorisations run one matrix at a time: jaxlib's CPU
LAPACK kernels split a batch of factorisations over XLA's intra-op thread pool and wait
for it, so two batched factorisations running at once (the actor's and the critic's) can
hold every thread of a small pool and wait for each other forever.
"""

from __future__ import annotations

from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.mappo.losses import RunningStats

_ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu}


def orthogonal(scale: float) -> Callable:
    """flax's orthogonal initialiser with gain ``scale``, the same values, whose
    ``jax.vmap`` over keys factorises one matrix at a time
    (``jax.custom_batching.sequential_vmap``) instead of as one batched LAPACK call."""
    init = nn.initializers.orthogonal(scale)

    def kernel_init(key, shape, dtype=jnp.float32):
        return jax.custom_batching.sequential_vmap(lambda k: init(k, shape, dtype))(key)

    return kernel_init


class Actor(nn.Module):
    """One agent's observation ``(..., obs_size)`` -> Gaussian mean ``(..., action_dim)``
    and log standard deviation ``(action_dim,)``."""

    action_dim: int
    hidden: tuple[int, ...]
    activation: str = "tanh"
    init_std: float = 0.3

    @nn.compact
    def __call__(self, obs):
        act = _ACTIVATIONS[self.activation]
        x = obs
        for width in self.hidden:
            x = act(nn.Dense(width, kernel_init=orthogonal(np.sqrt(2.0)))(x))
        mean = nn.Dense(self.action_dim, kernel_init=orthogonal(0.01))(x)
        log_std = self.param("log_std", nn.initializers.constant(np.log(self.init_std)), (self.action_dim,))
        return mean, log_std


class Critic(nn.Module):
    """Global state with an agent's one-hot id ``(..., state_size + n_agents)`` -> that
    agent's (normalised) value ``(...)``."""

    hidden: tuple[int, ...]
    activation: str = "tanh"

    @nn.compact
    def __call__(self, x):
        act = _ACTIVATIONS[self.activation]
        for width in self.hidden:
            x = act(nn.Dense(width, kernel_init=orthogonal(np.sqrt(2.0)))(x))
        return nn.Dense(1, kernel_init=orthogonal(1.0))(x)[..., 0]


def deterministic_policy_fn(actor: Actor, normalize_obs: bool = True, base: Callable | None = None) -> Callable:
    """``policy(key, obs, state, params, arrays) -> actions``: :func:`deterministic_policy`
    with the arrays an argument (traced), so one compiled evaluation serves every set."""

    def policy(key, obs, state, params, arrays):
        stats = RunningStats(mean=jnp.asarray(arrays["obs_mean"]), var=jnp.asarray(arrays["obs_var"]),
                             count=jnp.asarray(1.0))
        x = stats.normalize(obs.astype(jnp.float32)) if normalize_obs else obs.astype(jnp.float32)
        mean, _ = actor.apply(arrays["actor"], x)
        if base is not None:
            mean = mean + base(state, params)
        return jnp.clip(mean, -1.0, 1.0).astype(obs.dtype)

    return policy


def deterministic_policy(actor: Actor, arrays: dict, normalize_obs: bool = True, base: Callable | None = None
                         ) -> Callable:
    """``policy(key, obs, state, params) -> actions`` of one environment: the Gaussian's
    mean, clipped to ``[-1, 1]`` (the interface of :mod:`mysim_jax.tasks.evaluate`).
    ``base(state, params)``: actions the mean is added to (a residual policy's team)."""
    with_arrays = deterministic_policy_fn(actor, normalize_obs, base)

    def policy(key, obs, state, params):
        return with_arrays(key, obs, state, params, arrays)

    return policy

