"""The pieces of PPO's objective and MAPPO's normalisers, each a pure function.

* :func:`gae` — generalised advantage estimation over a rollout (Schulman et al. 2016);
* :func:`gaussian_log_prob`, :func:`gaussian_entropy` — the diagonal Gaussian policy;
* :func:`policy_loss` — PPO's clipped surrogate (Schulman et al. 2017), with the fraction
  of clipped ratios and an estimate of the KL divergence for monitoring;
* :func:`value_loss` — the clipped value loss of MAPPO (Yu et al. 2022);
* :class:`RunningStats` — running mean and variance (Chan et al.'s parallel update), used
  to normalise observations, states and value targets (MAPPO's "ValueNorm").
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct


def gae(rewards, values, dones, last_values, gamma: float, lam: float):
    """Advantages and returns ``(T, ...)`` of a rollout.

    ``rewards[t]`` and ``dones[t]`` follow the action at ``t``; ``dones[t]`` means the
    episode ended after step ``t`` (the next value is not bootstrapped: on a time limit, add
    ``gamma * V(final state)`` to the reward beforehand); ``values[t]`` is ``V(s_t)`` and
    ``last_values`` the value of the state after the rollout's last step.

        δ_t = r_t + γ (1 − d_t) V_{t+1} − V_t,     A_t = δ_t + γ λ (1 − d_t) A_{t+1}
    """
    not_done = 1.0 - dones.astype(values.dtype)

    def back(carry, x):
        next_value, next_adv = carry
        r, v, nd = x
        delta = r + gamma * nd * next_value - v
        adv = delta + gamma * lam * nd * next_adv
        return (v, adv), adv

    _, adv = jax.lax.scan(back, (last_values, jnp.zeros_like(last_values)), (rewards, values, not_done),
                          reverse=True)
    return adv, adv + values


def gaussian_log_prob(x, mean, log_std):
    """Log density of a diagonal Gaussian, summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z * z - log_std - 0.5 * math.log(2.0 * math.pi), axis=-1)


def gaussian_entropy(log_std):
    """Entropy of a diagonal Gaussian, summed over the last axis."""
    return jnp.sum(log_std + 0.5 * (1.0 + math.log(2.0 * math.pi)), axis=-1)


def policy_loss(log_prob, old_log_prob, advantages, clip_eps: float):
    """PPO's clipped surrogate, to minimise: ``−mean(min(ρA, clip(ρ, 1 ± ε)A))`` with
    ``ρ = exp(log π − log π_old)``. Returns ``(loss, clip_fraction, approx_kl)``
    (``approx_kl`` is the ``(ρ − 1) − log ρ`` estimator)."""
    log_ratio = log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    loss = -jnp.mean(jnp.minimum(unclipped, clipped))
    clip_fraction = jnp.mean((jnp.abs(ratio - 1.0) > clip_eps).astype(loss.dtype))
    approx_kl = jnp.mean((ratio - 1.0) - log_ratio)
    return loss, clip_fraction, approx_kl


def value_loss(values, old_values, targets, clip_eps: float):
    """``0.5 mean(max((V − R)², (V_old + clip(V − V_old, ±ε) − R)²))``: the value may move
    at most ``ε`` from the rollout's estimate before the loss stops rewarding it."""
    clipped = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
    return 0.5 * jnp.mean(jnp.maximum((values - targets) ** 2, (clipped - targets) ** 2))


def normalize_advantages(adv):
    return (adv - jnp.mean(adv)) / (jnp.std(adv) + 1e-8)


@struct.dataclass
class RunningStats:
    """Running mean and variance of a quantity of shape ``mean.shape`` (over every sample
    given to :meth:`update`)."""

    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray          # () samples seen (float, starts at a tiny prior)

    @classmethod
    def create(cls, shape=()) -> RunningStats:
        return cls(mean=jnp.zeros(shape, jnp.float32), var=jnp.ones(shape, jnp.float32),
                   count=jnp.asarray(1e-4, jnp.float32))

    def update(self, x) -> RunningStats:
        """Fold in the samples ``x`` ``(..., *mean.shape)``."""
        x = x.reshape((-1,) + self.mean.shape).astype(jnp.float32)
        n = jnp.asarray(x.shape[0], jnp.float32)
        b_mean = jnp.mean(x, axis=0)
        b_var = jnp.var(x, axis=0)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta ** 2 * self.count * n / total
        return RunningStats(mean=mean, var=m2 / total, count=total)

    @property
    def std(self):
        return jnp.sqrt(self.var + 1e-8)

    def normalize(self, x, clip: float = 10.0):
        return jnp.clip((x - self.mean) / self.std, -clip, clip)

    def denormalize(self, x):
        return x * self.std + self.mean
