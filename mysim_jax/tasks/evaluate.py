"""Evaluate a team on many episodes of a capture environment, batched.

**Episodes are numbered.** Episode ``i`` of an evaluation seeded with ``key`` is drawn from
``episode_key(key, i) = fold_in(key, i)`` alone: its reset from the first half of that key's
split, and its step ``t`` from ``fold_in(second half, t)`` (the policy's key and the
environment's, split from it). So the episodes, and every random draw inside them, are the
same whichever team flies them and whichever environment slot runs them: two teams
evaluated with one key fly the same episodes, and their outcomes can be compared episode
by episode (:func:`mysim_jax.tasks.sweep.paired_difference_interval`).

:func:`run_episodes` runs ``batch`` environment slots side by side (one jitted batch-last
:func:`mysim_jax.core.batching.vmap` of the episode runner,
:func:`mysim_jax.tasks.runner.rollout`, over ``chunk`` policy steps per call, a progress bar
between calls). Episodes ``0 .. batch − 1`` start in the slots; each slot holds the number
of the episode it starts next, and when its episode ends it resets into that one at once. Between calls, slots that have started their next
episode are given the next number from the queue, until ``n`` episodes have been handed
out; slots left without one idle until the last episode ends. Every episode runs to its
own end, so short episodes (fast failures) are not favoured, and results come back in
episode order.

**Resuming.** Given a ``checkpoint`` file, an :class:`Evaluator` call saves everything it
carries between calls (every slot's observation, state and episode bookkeeping, the rows of
the episodes already ended, the queue) every ``every_s`` seconds and when it ends
(:class:`Checkpoint`). A later call with the same file, episodes, key, batch, chunk and
``fingerprint`` (the caller's name for what it evaluates: scene, team, seed) goes on from
there with the same compiled program, so an interrupted evaluation ends with exactly the
numbers an uninterrupted one gives; a file that does not match is ignored and overwritten.

Policies are functions ``policy(key, obs, state, params) -> actions`` of one environment
(:func:`scripted_policy`, :func:`random_policy`, or a trained one), or with
``policy_args``, ``policy(key, obs, state, params, args)``: ``args`` (e.g. a network's
parameters) is traced, so an :class:`Evaluator` compiled once evaluates new parameters
without compiling again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.core import batching, parallel
from mysim_jax.core.machine import machine
from mysim_jax.config.env import FAILURES, REWARD_TERMS
from mysim_jax.tasks.runner import episode_key, episode_keys, rollout
from mysim_jax.tasks.sweep import wilson_interval

__all__ = ["episode_key", "episode_keys", "scripted_policy", "random_policy", "EpisodeStats", "Slots", "Evaluator",
           "Checkpoint", "files_digest", "source_digest", "arrays_digest", "run_episodes", "run_two_teams"]


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
    slot: np.ndarray                    # (n,) which environment slot ran it
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
            "machine": machine(),         # what wall_s was measured on
            "policy_steps": self.policy_steps,
        }


class Slots(NamedTuple):
    """What each environment slot of an :class:`Evaluator` carries besides its observation
    and state (per slot; a leading batch axis outside)."""

    episode: Any       # () int32, the episode it runs (-1: idle)
    t: Any             # () int32, the policy steps it has taken in that episode
    next: Any          # () int32, the episode it starts next (-1: none handed out yet)
    term_sum: Any      # (len(REWARD_TERMS),) the episode's sum of each weighted term, mean over agents


def _terms(info):
    """``(len(REWARD_TERMS),)`` this step's weighted terms, mean over agents."""
    return jnp.stack([jnp.mean(info["terms"][k]) for k in REWARD_TERMS])


def _outcome_row(step, slot: Slots):
    """A slot's row of one step: its episode, whether that episode ended here (an idle
    slot's steps end nothing), and the outcome it would have if so."""
    info = step.info
    return (slot.episode, info["done"] & (slot.episode >= 0), info["success"],
            jnp.stack([info["failures"][f] for f in FAILURES]), info["timeout"], info["episode_length"],
            jnp.mean(info["episode_return"]), slot.term_sum + _terms(info))


def _next_in_slot(step, slot: Slots, fresh):
    """Where a slot goes on from a step: an ended episode (or an idle slot) starts the
    slot's next episode from ``fresh`` (its reset ``(obs, state)``) if it has one, else the
    slot idles on; an unended one goes on."""
    done = step.info["done"]
    start = (done | (slot.episode < 0)) & (slot.next >= 0)
    obs_n, state_n = fresh
    obs = jnp.where(start, obs_n, step.next_obs)
    state = jax.tree.map(lambda a, b: jnp.where(start, a, b), state_n, step.next_state)
    term_sum = slot.term_sum + _terms(step.info)
    slot = Slots(episode=jnp.where(start, slot.next, jnp.where(done, -1, slot.episode)),
                 t=jnp.where(start | done, 0, slot.t + 1), next=jnp.where(start, -1, slot.next),
                 term_sum=jnp.where(start | done, jnp.zeros_like(term_sum), term_sum))
    return obs, state, slot


def files_digest(path, suffix: str = "") -> str:
    """SHA-256 of a file, or of every file (ending in ``suffix``) under a folder with its
    relative name; "" when ``path`` is not a file or folder (``scripted``, ``random``)."""
    root = Path(path)
    files = [root] if root.is_file() else sorted(f for f in root.rglob(f"*{suffix}") if f.is_file()) \
        if root.is_dir() else []
    if not files:
        return ""
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.relative_to(root) if f != root else f.name).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """SHA-256 of the package's source as this process first read it (files edited later
    do not change what the running process computes, so they do not change this either):
    part of a :class:`Checkpoint`'s fingerprint, so that only the same code resumes."""
    return files_digest(Path(__file__).resolve().parents[1], ".py")


def arrays_digest(tree) -> str:
    """SHA-256 of the arrays of a pytree (their shapes, types and bytes), e.g. a policy's."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        a = np.asarray(leaf)
        h.update(f"{a.shape}{a.dtype}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


_ROW_FIELDS = ("slot", "success", "failures", "timeout", "length", "returns", "terms")


@dataclass
class Checkpoint:
    """Where an :class:`Evaluator` call saves its progress and what it must match to be
    resumed: ``path`` (an ``.npz`` file, written atomically; its folder is made),
    ``fingerprint`` (the caller's description of what is evaluated: a resumed call must give
    the same one) and ``every_s`` (seconds of wall time between saves; it is also saved when
    the call ends)."""

    path: str | os.PathLike
    fingerprint: str = ""
    every_s: float = 300.0

    def meta(self, key, n: int, batch: int, chunk: int, carry) -> str:
        """What a saved file must match, as JSON: the fingerprint, the episodes, the key,
        the batch and chunk, and every carried array's shape and type."""
        return json.dumps({"fingerprint": self.fingerprint, "episodes": n, "batch": batch, "chunk": chunk,
                           "key": np.asarray(key).tolist(),
                           "carry": [[list(x.shape), str(x.dtype)] for x in jax.tree.leaves(carry)]})

    def save(self, meta: str, carry, rows: dict, queue: int, steps: int, wall_s: float) -> None:
        path = Path(self.path)
        path.parent.mkdir(parents=True, exist_ok=True)
        episodes = np.array(sorted(rows), np.int64)
        by_field = {f: np.array([rows[e][i] for e in episodes]) for i, f in enumerate(_ROW_FIELDS)}
        leaves = {f"carry_{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(carry))}
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(meta), queue=queue, steps=steps, wall_s=wall_s, episodes=episodes,
                     **{f"row_{k}": v for k, v in by_field.items()}, **leaves)
        os.replace(tmp, path)

    def load(self, meta: str, carry):
        """``(carry, rows, queue, steps, wall_s)`` from the file, or None when there is no
        file, it cannot be read or it does not match ``meta``."""
        try:
            with np.load(self.path) as z:
                if str(z["meta"]) != meta:
                    return None
                treedef = jax.tree.structure(carry)
                leaves = [jnp.asarray(z[f"carry_{i}"]) for i in range(treedef.num_leaves)]
                episodes = z["episodes"]
                fields = [z[f"row_{f}"] if episodes.size else None for f in _ROW_FIELDS]
                rows = {int(e): tuple(v[j] for v in fields) for j, e in enumerate(episodes)}
                return (jax.tree.unflatten(treedef, leaves), rows, int(z["queue"]), int(z["steps"]),
                        float(z["wall_s"]))
        except (OSError, KeyError, ValueError):
            return None


class Evaluator:
    """Numbered episodes (module docstring) of ``policy`` on ``env``, ``batch`` slots side
    by side: ``evaluator(key, n_episodes, policy_args)`` runs episodes ``0 .. n − 1`` drawn
    from ``key`` and returns their :class:`EpisodeStats`. The batched step is compiled once
    per batch size (``min(batch, n)``); keys, episode counts and ``policy_args`` are
    arguments, so evaluating other episodes or other network parameters compiles nothing.
    ``policy(key, obs, state, params, args)``. Each call runs ``chunk`` steps of every slot
    with :func:`mysim_jax.tasks.runner.rollout`. ``env_batching`` batches the slots as
    :func:`mysim_jax.core.batching.batch` says (``"batch_last"``, the CPU's choice, or
    ``"vmap"``). A call given a :class:`Checkpoint` saves its progress and resumes from it
    (module docstring)."""

    def __init__(self, env, params, policy, batch: int, chunk: int = 8, env_batching: str = "batch_last"):
        if batch < 1 or chunk < 1:
            raise ValueError("Evaluator: batch and chunk must be at least 1")
        self.env, self.params = env, params
        self.batch, self.chunk = batch, chunk
        self._n_terms = len(REWARD_TERMS)

        def advance(carry, args, key):
            # a slot starts at most one episode per call (its number is handed out between
            # calls), so that episode's first state is computed once per call, not per step
            obs, state, slots = carry
            k_reset, _, _ = episode_keys(key, jnp.maximum(slots.next, 0), 0)
            fresh = env.reset(k_reset, params)
            return rollout(env, params, lambda k, o, s, p: policy(k, o, s, p, args), obs, state, length=chunk,
                           keys=lambda _, slot: episode_keys(key, jnp.maximum(slot.episode, 0), slot.t)[1:],
                           record=_outcome_row, update=lambda step, slot: _next_in_slot(step, slot, fresh),
                           aux=slots, auto_reset=False)

        # slots begin idle (episode -1) on placeholder zeros: their first step starts their
        # first episode from ``advance``'s reset, so no separate reset program is compiled
        self._blank = jax.eval_shape(lambda: env.reset(jax.random.PRNGKey(0), params))
        self._float = self._blank[0].dtype              # the scene's precision (float32 or float64)
        block = batching.chunk_for(self._blank[1]) if env_batching == "batch_last" else None
        self._batched = batching.batch(advance, env_batching, in_axes=(0, None, None), chunk=block)
        self._compiled = {}

    def _advance(self, batch: int):
        # batch axis last inside, in cache-sized blocks (mysim_jax.core.batching); split over
        # this process's devices when it has several
        if batch not in self._compiled:
            self._compiled[batch] = parallel.jit_envs(self._batched, batch, in_axes=(0, None, None))
        return self._compiled[batch]

    def __call__(self, key, n_episodes: int, policy_args=None, progress: bool = False,
                 desc: str = "episodes", checkpoint: Checkpoint | None = None) -> EpisodeStats:
        if n_episodes < 1:
            raise ValueError("Evaluator: n_episodes must be at least 1")
        n = n_episodes
        batch = min(self.batch, n)
        advance = self._advance(batch)
        t0 = time.perf_counter()
        first = np.arange(batch)
        obs, state = jax.tree.map(lambda x: jnp.zeros((batch,) + x.shape, x.dtype), self._blank)
        queue = batch                                   # the next episode number to hand out
        carry = (obs, state, Slots(episode=jnp.full(batch, -1, jnp.int32), t=jnp.zeros(batch, jnp.int32),
                                   next=jnp.asarray(first, jnp.int32),
                                   term_sum=jnp.zeros((batch, self._n_terms), self._float)))
        rows = {}
        steps, wall_before = 0, 0.0
        if checkpoint is not None:
            meta = checkpoint.meta(key, n, batch, self.chunk, carry)
            resumed = checkpoint.load(meta, carry)
            if resumed is not None:
                carry, rows, queue, steps, wall_before = resumed
            saved = time.perf_counter()
        bar = None
        if progress:
            bar = tqdm(total=n, initial=len(rows), desc=desc, unit="ep")
        while len(rows) < n:
            carry, out = advance(carry, policy_args, key)
            ep, finishing, success, failures, timeout, length, ret, terms = jax.tree.map(np.asarray, out)
            steps += batch * self.chunk
            before = len(rows)
            for b, s in zip(*np.nonzero(finishing)):
                rows[int(ep[b, s])] = (b, success[b, s], failures[b, s], timeout[b, s], length[b, s], ret[b, s],
                                       terms[b, s])
            if bar is not None:
                bar.update(len(rows) - before)
            # slots that have started their next episode get another number
            nxt = np.asarray(carry[2].next)
            free = np.flatnonzero(nxt < 0)[:max(0, n - queue)]
            if free.size:
                nxt = nxt.copy()
                nxt[free] = np.arange(queue, queue + free.size)
                queue += free.size
                carry = (carry[0], carry[1], carry[2]._replace(next=jnp.asarray(nxt, jnp.int32)))
            if checkpoint is not None and time.perf_counter() - saved >= checkpoint.every_s and len(rows) < n:
                checkpoint.save(meta, carry, rows, queue, steps, wall_before + time.perf_counter() - t0)
                saved = time.perf_counter()
        if bar is not None:
            bar.close()
        wall = wall_before + time.perf_counter() - t0
        if checkpoint is not None:
            checkpoint.save(meta, carry, rows, queue, steps, wall)
        order = [rows[i] for i in range(n)]
        fail = np.stack([r[2] for r in order])
        term_rows = np.stack([r[6] for r in order])
        return EpisodeStats(
            success=np.array([r[1] for r in order], bool),
            failures={f: fail[:, i].astype(bool) for i, f in enumerate(FAILURES)},
            timeout=np.array([r[3] for r in order], bool),
            length=np.array([r[4] for r in order], int),
            returns=np.array([r[5] for r in order], float),
            terms={t: term_rows[:, i] for i, t in enumerate(REWARD_TERMS)},
            slot=np.array([r[0] for r in order], int), wall_s=wall, policy_steps=steps,
            extra={"resumed_wall_s": wall_before} if wall_before else {})


def run_episodes(env, params, policy, n_episodes: int, batch: int, key, chunk: int = 8,
                 progress: bool = True, policy_args=None) -> EpisodeStats:
    """Run episodes ``0 .. n_episodes − 1`` drawn from ``key`` (module docstring), ``batch``
    at a time. ``policy(key, obs, state, params)``, or with ``policy_args``
    ``policy(key, obs, state, params, args)``. ``wall_s`` includes compiling."""
    if n_episodes < 1 or batch < 1:
        raise ValueError("run_episodes: n_episodes and batch must be at least 1")
    call = policy if policy_args is not None else (lambda k, o, s, p, a: policy(k, o, s, p))
    t0 = time.perf_counter()
    stats = Evaluator(env, params, call, batch, chunk)(key, n_episodes, policy_args, progress=progress)
    stats.wall_s = time.perf_counter() - t0
    return stats


def run_two_teams(env, params, policy, other, n_episodes: int, batch: int, key, chunk: int = 8,
                  progress: bool = True) -> tuple[EpisodeStats, EpisodeStats]:
    """Episodes ``0 .. n_episodes − 1`` flown by ``policy`` and then by ``other`` (both
    ``policy(key, obs, state, params)``): one compiled program serves both (an argument
    picks the team), so the second team compiles nothing. Each step evaluates both
    teams' actions and keeps one."""
    if n_episodes < 1 or batch < 1:
        raise ValueError("run_two_teams: n_episodes and batch must be at least 1")

    def either(k, obs, state, p, use_other):
        return jnp.where(use_other, other(k, obs, state, p), policy(k, obs, state, p))

    evaluator = Evaluator(env, params, either, batch, chunk)
    first = evaluator(key, n_episodes, jnp.bool_(False), progress=progress, desc="episodes")
    second = evaluator(key, n_episodes, jnp.bool_(True), progress=progress, desc="compared team")
    return first, second
