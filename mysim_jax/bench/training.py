"""Training throughput: what one MAPPO iteration costs against the environment alone.

Three AOT-compiled calls on the same ``num_envs`` environments, timed round-robin
(:func:`mysim_jax.bench.timing.time_round_robin`):

* ``iteration`` — :meth:`Trainer.iteration`: the rollout (policy + environment, ``num_steps``
  team steps) and the update (GAE, every epoch and minibatch);
* ``rollout`` — the rollout alone (policy sampling, critic values, environment steps);
* ``env`` — ``num_steps`` batched environment steps with zero actions (hover in velocity
  mode), no networks: the environment's own throughput in the same layout
  (:func:`mysim_jax.core.batching.vmap`, the trainer's blocks).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from mysim_jax.core import batching
from mysim_jax.bench.timing import aot_compile, median, time_round_robin


@dataclass
class TrainingThroughput:
    num_envs: int
    num_steps: int
    times: dict[str, list[float]]      # call -> seconds per call (counted rounds)
    compile_s: dict[str, float]

    def steps_per_s(self, key: str) -> float:
        return self.num_envs * self.num_steps / median(self.times[key])


def measure(trainer, key, repeats: int = 3, section: str = "g") -> TrainingThroughput:
    """Time the three calls of the module docstring for ``trainer`` (a
    :class:`~mysim_jax.mappo.trainer.Trainer`)."""
    c = trainer.config
    env, env_params = trainer.env, trainer.env_params
    ts = trainer.init(key)

    one = jax.eval_shape(lambda k: env.reset(k, env_params)[1], jax.random.PRNGKey(0))
    block = batching.chunk_for(one)

    def env_only(k, state):
        def body(s, kk):
            return env.step(kk, s, jnp.zeros(env.action_shape, jnp.float32), env_params)[1], None
        return jax.lax.scan(body, state, jax.random.split(k, c.num_steps))[0]

    keys = jax.random.split(jax.random.PRNGKey(1), c.num_envs)
    compiled, compile_s = {}, {}
    compiled["iteration"], compile_s["iteration"], _ = aot_compile(jax.jit(trainer._iteration), ts)
    compiled["rollout"], compile_s["rollout"], _ = aot_compile(jax.jit(trainer._rollout), ts)
    compiled["env"], compile_s["env"], _ = aot_compile(jax.jit(batching.vmap(env_only, chunk=block)), keys,
                                                     ts.env_state)
    calls = {"iteration": lambda: compiled["iteration"](ts), "rollout": lambda: compiled["rollout"](ts),
             "env": lambda: compiled["env"](keys, ts.env_state)}
    times = time_round_robin(calls, repeats, section=section)
    return TrainingThroughput(c.num_envs, c.num_steps, times, compile_s)
