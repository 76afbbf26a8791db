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

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax import batching, parallel
from mysim_jax.build import build
from mysim_jax.io.trajectory import trajectory_columns
from mysim_jax.sim import rollout, steps_per_output
from mysim_jax.tasks.outcome import CaptureOutcome, capture_outcome
from mysim_jax.tasks.scripted import team_policy
from mysim_jax.tasks.target import spawn_target


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
    return max(0.0, centre - half), min(1.0, centre + half)


def capture_sweep(config, seeds) -> SweepResult:
    """Run ``config`` (a capture SceneConfig with ``net``, ``target`` and ``team``) once per seed."""
    import time

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
