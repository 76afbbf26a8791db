"""Monte Carlo over target spawns: the same capture scene from many seeds, batched with ``vmap``.

:func:`capture_sweep` draws the target's spawn for each seed (:func:`spawn_target` with
``jax.random.PRNGKey(seed)``, exactly as :func:`mysim_jax.build.build` does for
``target.seed``), runs all of them as one jitted ``vmap`` of :func:`mysim_jax.sim.rollout`
with the scene's team policy, and judges each run with
:func:`mysim_jax.tasks.outcome.capture_outcome` on its output grid.
"""

from __future__ import annotations

import math
import types
from dataclasses import dataclass
import time

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import batching, parallel
from mysim_jax.build import build
from mysim_jax.io.trajectory import trajectory_columns
from mysim_jax.driver import steps_per_output
from mysim_jax.sim import rollout
from mysim_jax.tasks.outcome import CaptureOutcome, capture_outcome
from mysim_jax.tasks.scripted import team_policy
from mysim_jax.effects.target import spawn_target


@dataclass
class SweepResult:
    seeds: list[int]
    outcomes: list[CaptureOutcome]
    spawn: np.ndarray            # (n, 3) m, the target's start
    min_uav_height: np.ndarray   # (n,) m, lowest UAV centre over the run
    wall_s: float                # the batched run (compile included)

    @property
    def caught(self) -> int:
        return sum(o.caught for o in self.outcomes)


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` of a success rate ``k / n`` (95 % for z = 1.96):
    unlike ``p ± z √(p(1−p)/n)`` it stays inside [0, 1] and is not empty at k = 0 or n."""
    if n < 1:
        raise ValueError("wilson_interval: n must be at least 1")
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # at k = 0 (k = n) the lower (upper) bound is exactly 0 (1); computed, it can land a
    # rounding error inside, above the rate itself (an error bar of negative length)
    low = 0.0 if k == 0 else max(0.0, centre - half)
    high = 1.0 if k == n else min(1.0, centre + half)
    return low, high


def paired_difference_interval(a, b, z: float = 1.96) -> tuple[float, float, float]:
    """``(d, low, high)``: the difference ``d = rate(a) - rate(b)`` of two success rates
    measured on the same episodes (``a``, ``b``: ``(n,)`` bool, episode ``i`` of both runs
    drawn alike) and its 95 % interval, Newcombe's hybrid score method for paired data
    (Stat. Med. 17, 1998, method 10): the Wilson intervals ``[l1, u1]``, ``[l2, u2]`` of the
    two rates combined with the phi correlation of the paired outcomes::

        low  = d - √((p1 - l1)² - 2 φ (p1 - l1)(u2 - p2) + (u2 - p2)²)
        high = d + √((u1 - p1)² - 2 φ (u1 - p1)(p2 - l2) + (p2 - l2)²)

    Pairing narrows the interval when the outcomes agree episode by episode."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape or a.ndim != 1 or len(a) < 1:
        raise ValueError(f"paired_difference_interval: two (n,) outcome arrays of one length, got {a.shape}, {b.shape}")
    n = len(a)
    both, only_a, only_b, neither = (int(np.sum(x)) for x in (a & b, a & ~b, ~a & b, ~a & ~b))
    p1, p2 = (both + only_a) / n, (both + only_b) / n
    l1, u1 = wilson_interval(both + only_a, n, z)
    l2, u2 = wilson_interval(both + only_b, n, z)
    margins = (both + only_a) * (only_b + neither) * (both + only_b) * (only_a + neither)
    phi = (both * neither - only_a * only_b) / math.sqrt(margins) if margins > 0 else 0.0
    d = p1 - p2
    low = d - math.sqrt(max((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2, 0.0))
    high = d + math.sqrt(max((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2, 0.0))
    return d, max(low, -1.0), min(high, 1.0)


def capture_sweep(config, seeds) -> SweepResult:
    """Run ``config`` (a capture SceneConfig with ``net``, ``target`` and ``team``) once per seed."""
    seeds = list(seeds)
    scene, params, state = build(config)
    policy = team_policy(config, scene)
    run = config.run_settings()
    every = steps_per_output(scene, run)
    n_out = int(round(run.t_end / run.output_dt))
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    starts = jax.vmap(lambda k: spawn_target(scene, params, state, k))(keys)
    t0 = time.perf_counter()
    batched = batching.vmap(lambda s: rollout(scene, params, s, n_out * every, every, policy)[1],
                            chunk=batching.chunk_for(state))
    saved = parallel.jit_envs(batched, len(seeds))(starts)
    saved, starts = jax.tree.map(np.asarray, saved), jax.tree.map(np.asarray, starts)
    wall = time.perf_counter() - t0
    uavs = [scene.body_names.index(q.body) for q in config.quadrotors]
    target = scene.body_names.index(config.target.name)
    outcomes, low = [], []
    for e in range(len(seeds)):
        phys = jax.tree.map(lambda a, b: np.concatenate([a[e][None], b[e]]), starts.phys, saved.phys)
        acc = types.SimpleNamespace(point_acc=np.zeros_like(phys.point_pos), body_acc=np.zeros_like(phys.body_pos))
        traj = types.SimpleNamespace(time=np.arange(n_out + 1) * run.output_dt, phys=phys, acc=acc)
        outcomes.append(capture_outcome(trajectory_columns(scene, traj), config))
        low.append(float(phys.body_pos[:, uavs, 2].min()))
    return SweepResult(seeds=seeds, outcomes=outcomes, spawn=starts.phys.body_pos[:, target],
                       min_uav_height=np.asarray(low), wall_s=wall)
