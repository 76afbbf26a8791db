"""Evaluate a team on many episodes of a capture environment, batched.

:func:`run_episodes` runs ``batch`` environments side by side (one jitted batch-last
``mysim_jax.batching.vmap`` of
:meth:`CaptureEnv.step` scanned over ``chunk`` policy steps per call, a progress bar
between calls) until every environment has finished ``ceil(n / batch)`` episodes, and
keeps exactly those first episodes of every slot (the first ``n`` of them in slot order).
Keeping a fixed number of episodes per slot, rather than every episode that ends within a
time window, avoids favouring short episodes (fast failures) in the rates.

Policies are functions ``policy(key, obs, state, params) -> actions`` of one environment
(:func:`scripted_policy`, :func:`random_policy`, or a trained one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax import batching, parallel
from mysim_jax.tasks.env_config import FAILURES, REWARD_TERMS
from mysim_jax.tasks.sweep import wilson_interval


def scripted_policy(env):
    """The scripted intercept team (:meth:`CaptureEnv.scripted_actions`)."""
    def policy(key, obs, state, params):
        return env.scripted_actions(state, params)
    return policy


def random_policy(env):
    """Uniform random actions in ``[-1, 1]``."""
    def policy(key, obs, state, params):
        return env.random_actions(key).astype(obs.dtype)
    return policy


@dataclass
class EpisodeStats:
    """One row per evaluated episode."""

    success: np.ndarray                 # (n,) bool
    failures: dict[str, np.ndarray]     # name -> (n,) bool
    timeout: np.ndarray                 # (n,) bool
    length: np.ndarray                  # (n,) policy steps
    returns: np.ndarray                 # (n,) mean over agents of the episode's return
    terms: dict[str, np.ndarray]        # term -> (n,) episode sum of the weighted term, mean over agents
    slot: np.ndarray                    # (n,) which batched environment ran it
    wall_s: float = 0.0                 # the batched run, compile included
    policy_steps: int = 0               # policy steps taken in all (every slot, every step)
    extra: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.success)

    def rate(self, flags) -> dict:
        k = int(np.sum(flags))
        lo, hi = wilson_interval(k, self.n)
        return {"count": k, "rate": k / self.n, "interval95": [lo, hi]}

    def summary(self) -> dict:
        """Rates with 95 % Wilson intervals, mean return and terms, mean length."""
        return {
            "episodes": self.n,
            "success": self.rate(self.success),
            "failures": {k: self.rate(v) for k, v in self.failures.items()},
            "timeout": self.rate(self.timeout),
            "mean_length_steps": float(np.mean(self.length)),
            "mean_return": float(np.mean(self.returns)),
            "mean_terms": {k: float(np.mean(v)) for k, v in self.terms.items()},
            "wall_s": self.wall_s,
            "policy_steps": self.policy_steps,
        }


def run_episodes(env, params, policy, n_episodes: int, batch: int, key, chunk: int = 25,
                 progress: bool = True) -> EpisodeStats:
    """Run ``n_episodes`` episodes (module docstring). ``key`` seeds everything: slot
    ``b`` resets from ``fold_in(key, b)`` and steps with keys split from its own."""
    import time

    if n_episodes < 1 or batch < 1:
        raise ValueError("run_episodes: n_episodes and batch must be at least 1")
    batch = min(batch, n_episodes)
    quota = math.ceil(n_episodes / batch)

    def one(carry, _):
        k, obs, state = carry
        k, k_act, k_step = jax.random.split(k, 3)
        actions = policy(k_act, obs, state, params)
        obs, state, reward, terminated, truncated, info = env.step(k_step, state, actions, params)
        row = (info["done"], info["success"], jnp.stack([info["failures"][f] for f in FAILURES]), info["timeout"],
               info["episode_length"], jnp.mean(info["episode_return"]),
               jnp.stack([jnp.mean(info["terms"][t]) for t in REWARD_TERMS]))
        return (k, obs, state), row

    def advance(carry):
        return jax.lax.scan(one, carry, None, length=chunk)

    def start(k):
        k_reset, k_run = jax.random.split(k)
        obs, state = env.reset(k_reset, params)
        return k_run, obs, state

    carry = jax.jit(jax.vmap(start))(jax.vmap(lambda b: jax.random.fold_in(key, b))(jnp.arange(batch)))
    # batch axis last inside, in cache-sized blocks (mysim_jax.batching); split over the
    # devices when there are several
    block = batching.chunk_for(jax.tree.map(lambda x: x[0], carry[2]))
    advance = parallel.jit_envs(batching.vmap(advance, chunk=block), batch)
    done_count = np.zeros(batch, int)
    term_sums = np.zeros((batch, len(REWARD_TERMS)))
    rows = []
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=quota * batch, desc="episodes", unit="ep")
    t0 = time.perf_counter()
    steps = 0
    while done_count.min() < quota:
        carry, out = advance(carry)
        done, success, failures, timeout, length, ret, terms = jax.tree.map(np.asarray, out)
        steps += batch * chunk
        before = np.minimum(done_count, quota).sum()
        for b in range(batch):
            for s in range(chunk):
                if done_count[b] >= quota:
                    break
                term_sums[b] += terms[b, s]
                if done[b, s]:
                    rows.append((b, done_count[b], success[b, s], failures[b, s], timeout[b, s], length[b, s],
                                 ret[b, s], term_sums[b].copy()))
                    done_count[b] += 1
                    term_sums[b] = 0.0
        if bar is not None:
            bar.update(int(np.minimum(done_count, quota).sum() - before))
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    rows.sort(key=lambda r: (r[1], r[0]))      # episode index within slot, then slot
    rows = rows[:n_episodes]
    fail = np.stack([r[3] for r in rows])
    term_rows = np.stack([r[7] for r in rows])
    return EpisodeStats(
        success=np.array([r[2] for r in rows], bool),
        failures={f: fail[:, i].astype(bool) for i, f in enumerate(FAILURES)},
        timeout=np.array([r[4] for r in rows], bool),
        length=np.array([r[5] for r in rows], int),
        returns=np.array([r[6] for r in rows], float),
        terms={t: term_rows[:, i] for i, t in enumerate(REWARD_TERMS)},
        slot=np.array([r[0] for r in rows], int), wall_s=wall, policy_steps=steps)
