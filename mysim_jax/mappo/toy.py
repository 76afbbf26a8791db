"""A small cooperative task with the capture environment's interface, for tests and smoke
runs of the trainer: ``env.builtin: reach`` in a training file.

Each of ``n_agents`` point agents in the plane must reach its own landmark. Positions and
landmarks are drawn uniformly in ``[-1, 1]²`` at reset; an action ``(2,)`` in ``[-1, 1]``
is a velocity of at most ``speed`` m/s held for ``dt``. Reward per agent: minus its
distance to its landmark, plus 1 for every agent on the step all are within ``radius``
(which ends the episode, ``terminated``); ``truncated`` after ``max_steps``.
Observations per agent: its position, its landmark relative to it, every other agent
relative to it, its one-hot id. The global state: every position and landmark.

A random policy scores about -0.9 per agent per step; one that heads straight for its
landmark, about -0.3 and finishes in ~10 steps: learning shows within a few thousand
updates.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class ReachState:
    pos: jnp.ndarray        # (n_agents, 2)
    goal: jnp.ndarray       # (n_agents, 2)
    steps: jnp.ndarray      # () int32
    returns: jnp.ndarray    # (n_agents,)


@struct.dataclass
class ReachParams:
    speed: jnp.ndarray      # () m/s


@dataclass(frozen=True)
class ReachEnv:
    n_agents: int = 2
    dt: float = 0.1
    max_steps: int = 25
    radius: float = 0.1

    @property
    def obs_size(self) -> int:
        return 2 + 2 + 2 * (self.n_agents - 1) + self.n_agents

    @property
    def state_size(self) -> int:
        return 4 * self.n_agents + 1

    @property
    def action_shape(self) -> tuple[int, int]:
        return (self.n_agents, 2)

    @property
    def agents(self) -> tuple[str, ...]:
        return tuple(f"agent{i}" for i in range(self.n_agents))

    def default_params(self) -> ReachParams:
        return ReachParams(speed=jnp.asarray(1.0, jnp.float32))

    def _fresh(self, key) -> ReachState:
        kp, kg = jax.random.split(key)
        n = self.n_agents
        return ReachState(pos=jax.random.uniform(kp, (n, 2), minval=-1.0, maxval=1.0),
                          goal=jax.random.uniform(kg, (n, 2), minval=-1.0, maxval=1.0),
                          steps=jnp.int32(0), returns=jnp.zeros((n,)))

    def observe(self, state: ReachState):
        n = self.n_agents
        others = jnp.asarray([[j for j in range(n) if j != i] for i in range(n)], jnp.int32).reshape(n, n - 1)
        rel = (state.pos[others] - state.pos[:, None, :]).reshape(n, 2 * (n - 1))
        return jnp.concatenate([state.pos, state.goal - state.pos, rel, jnp.eye(n)], axis=-1)

    def global_state(self, state: ReachState):
        left = 1.0 - state.steps / self.max_steps
        return jnp.concatenate([state.pos.reshape(-1), state.goal.reshape(-1), left[None]])

    def reset(self, key, params: ReachParams):
        state = self._fresh(key)
        return self.observe(state), state

    def step(self, key, state: ReachState, actions, params: ReachParams):
        """``(obs, state, reward, terminated, truncated, info)``: :meth:`step_env`, then a
        fresh episode drawn from ``key`` where this one ended (auto-reset; ``info`` describes
        the ended episode, ``info["global_state"]`` is the new one's)."""
        _, after, reward, success, timeout, info = self.step_env(key, state, actions, params)
        new = jax.tree.map(lambda f, a_: jnp.where(info["done"], f, a_), self._fresh(key), after)
        info["global_state"] = self.global_state(new)
        return self.observe(new), new, reward, success, timeout, info

    def step_env(self, key, state: ReachState, actions, params: ReachParams):
        """One step without the reset: the state the step reached even when the episode
        ends (``info["final_global_state"]`` equals ``info["global_state"]``)."""
        a = jnp.clip(jnp.where(jnp.isfinite(actions), actions, 0.0), -1.0, 1.0)
        pos = state.pos + params.speed * self.dt * a
        dist = jnp.linalg.norm(pos - state.goal, axis=-1)
        success = jnp.all(dist < self.radius)
        reward = -dist + success.astype(jnp.float32)
        steps = state.steps + 1
        timeout = (steps >= self.max_steps) & ~success
        returns = state.returns + reward
        after = ReachState(pos=pos, goal=state.goal, steps=steps, returns=returns)
        info = {
            "success": success, "done": success | timeout, "timeout": timeout,
            "episode_return": returns, "episode_length": steps,
            "final_global_state": self.global_state(after),
            "global_state": self.global_state(after),
        }
        return self.observe(after), after, reward, success, timeout, info
