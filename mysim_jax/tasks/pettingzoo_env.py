"""The capture environment as a PettingZoo ``ParallelEnv``: NumPy in, NumPy out.

    env = CaptureParallelEnv(load_config("configs/capture_falling.yaml", ["env={}"]))
    obs, infos = env.reset(seed=0)
    while env.agents:
        actions = {agent: policy(obs[agent]) for agent in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)

A host-side wrapper around the functional :class:`~mysim_jax.tasks.capture.CaptureEnv`
(one environment, no batching: for training at scale use the functional env under
``vmap``). Its ``reset`` and ``step`` run jitted, compiled once per environment structure
(the static :class:`CaptureEnv` is a static argument, so wrappers of equal environments
share the compiled code); the state and the PRNG key stay on the device between calls.

**Agents.** ``possible_agents`` are the UAV body names. The team ends together: every
agent is live from ``reset`` until the step that terminates or truncates the episode,
which reports the same flags for all and leaves ``agents == []``; call ``reset`` then
(stepping a finished episode is a RuntimeError).

**Actions** ``{agent: array (3,)}``, one normalised setpoint per UAV (module docstring of
:mod:`mysim_jax.tasks.capture`). Every live agent must act. A missing or unknown agent,
a wrong shape, a non-numeric or a non-finite (NaN, inf) value is a ValueError naming the
agent. Values outside ``[-1, 1]`` are clipped to it (by the functional env).

**Observations** ``float32 (obs_size,)`` per agent; ``state()`` the noise-free global state
``float32 (state_size,)`` for a centralised critic. At the step that ends an episode both
are the episode's last, as is the state ``render()`` draws until ``reset``: the wrapper
steps with the functional env's ``step_env``, which does not reset (``reset`` starts the
next episode).

**Infos** per agent at each step: ``terms`` (the agent's weighted reward terms, floats,
summing to its reward), ``success``, ``failed``, ``failures`` (name -> bool, the checks of
:data:`~mysim_jax.config.env.FAILURES`), ``timeout``, ``target_held``, ``touching`` and the
episode's running ``episode_return`` (the agent's) and ``episode_length`` (steps). The
infos of ``reset`` are empty dicts.

**Seeding.** ``reset(seed)`` starts a JAX PRNG key ``jax.random.key(seed)`` (``0 <= seed
< 2**32``); ``reset()`` continues the current key, or on the first reset starts one from a
seed drawn by ``numpy.random.default_rng()``. Same seed and same actions give the same
observations, rewards and infos bit for bit (on the same machine and JAX version).

**Rendering.** ``render_mode="rgb_array"``: ``render()`` draws the current state (top
view and side view of the UAVs, the net's knots and the target) with matplotlib and
returns an ``(H, W, 3) uint8`` image; with ``render_mode=None`` it warns and returns None.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import gymnasium
import jax
import numpy as np
from gymnasium import spaces
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from pettingzoo import ParallelEnv

from mysim_jax.tasks.capture import CaptureEnv, EnvParams, make_env

ACTION_SIZE = 3          # one setpoint per UAV
SEED_LIMIT = 2 ** 32     # seeds are uint32 (jax.random.key truncates larger ones without x64)


@functools.partial(jax.jit, static_argnums=0)
def _reset(env: CaptureEnv, key, params: EnvParams):
    """``(key, obs, state, global_state)``: a fresh episode and the advanced key."""
    key, sub = jax.random.split(key)
    obs, state = env.reset(sub, params)
    return key, obs, state, env.global_state(state)


@functools.partial(jax.jit, static_argnums=0)
def _step(env: CaptureEnv, key, state, actions, params: EnvParams):
    """``(key, state, (obs, reward, terminated, truncated, info))``: one policy step (no reset)."""
    key, sub = jax.random.split(key)
    obs, state, reward, terminated, truncated, info = env.step_env(sub, state, actions, params)
    return key, state, (obs, reward, terminated, truncated, info)


class CaptureParallelEnv(ParallelEnv):
    """PettingZoo parallel API of a capture scene (module docstring).

    ``CaptureParallelEnv(config, render_mode=None)`` from a SceneConfig with ``net:``,
    ``target:`` and ``env:`` blocks, or :meth:`from_env` from a built ``(env, params)``.
    """

    metadata: ClassVar[dict] = {"name": "mysim_jax_capture_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, config, render_mode: str | None = None):
        env, params = make_env(config)
        self._setup(env, params, render_mode)

    @classmethod
    def from_env(cls, env: CaptureEnv, params: EnvParams, render_mode: str | None = None) -> CaptureParallelEnv:
        """The wrapper of an already built functional environment."""
        self = cls.__new__(cls)
        self._setup(env, params, render_mode)
        return self

    def _setup(self, env: CaptureEnv, params: EnvParams, render_mode: str | None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: {render_mode!r} is not one of {self.metadata['render_modes']} or None")
        self.capture_env = env
        self.env_params = params
        self.render_mode = render_mode
        self.possible_agents = list(env.agents)
        self.agents: list[str] = []
        self._action_dtype = np.dtype(env.scene.dtype)
        # one space object per agent (each seeds and samples on its own), returned as is
        self.observation_spaces = {a: spaces.Box(-np.inf, np.inf, (env.obs_size,), np.float32)
                                   for a in self.possible_agents}
        self.action_spaces = {a: spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32) for a in self.possible_agents}
        self.state_space = spaces.Box(-np.inf, np.inf, (env.state_size,), np.float32)
        self._key = None           # JAX PRNG key (device), set by the first reset
        self._state = None         # EnvState (device)
        self._global_state = None  # (state_size,) float32 NumPy
        self._figure = None

    # --- spaces -----------------------------------------------------------------------
    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[self._check_agent(agent)]

    def _check_agent(self, agent) -> str:
        if agent not in self.observation_spaces:
            raise KeyError(f"unknown agent {agent!r}: the agents are {self.possible_agents}")
        return agent

    # --- the API ----------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        """``(observations, infos)`` of a new episode (``options`` is accepted and unused)."""
        if seed is not None:
            self._key = jax.random.key(_check_seed(seed))
        elif self._key is None:
            self._key = jax.random.key(int(np.random.default_rng().integers(SEED_LIMIT)))
        self._key, obs, self._state, global_state = _reset(self.capture_env, self._key, self.env_params)
        obs, global_state = jax.device_get((obs, global_state))
        self._global_state = np.asarray(global_state, np.float32)
        self.agents = list(self.possible_agents)
        return self._per_agent(obs), {a: {} for a in self.agents}

    def step(self, actions: dict):
        """``(observations, rewards, terminations, truncations, infos)`` of one policy step."""
        if self._state is None or not self.agents:
            raise RuntimeError("step: no episode is running (call reset() first; an episode that ended needs a reset)")
        stacked = self._check_actions(actions)
        self._key, self._state, out = _step(self.capture_env, self._key, self._state, stacked, self.env_params)
        obs, reward, terminated, truncated, info = jax.device_get(out)
        self._global_state = np.asarray(info["global_state"], np.float32)
        terminated, truncated = bool(terminated), bool(truncated)
        agents = self.agents
        observations = self._per_agent(obs)
        rewards = {a: float(reward[i]) for i, a in enumerate(agents)}
        terminations = {a: terminated for a in agents}
        truncations = {a: truncated for a in agents}
        infos = self._infos(info, terminated)
        if terminated or truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The global state ``float32 (state_size,)`` (after a terminal step: the episode's last)."""
        if self._global_state is None:
            raise RuntimeError("state: call reset() first")
        return self._global_state.copy()

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("You are calling render method without specifying any render mode "
                                  f"(CaptureParallelEnv(..., render_mode=...) with one of {self.metadata['render_modes']}).")
            return None
        if self._state is None:
            raise RuntimeError("render: call reset() first")
        return self._render_rgb()

    def close(self) -> None:
        self._figure = None

    # --- conversions ------------------------------------------------------------------
    def _check_actions(self, actions) -> np.ndarray:
        """The actions of the live agents, stacked ``(n_agents, 3)``; ValueError naming the
        agent on anything a policy should not send (TypeError if not a dict)."""
        if not isinstance(actions, dict):
            raise TypeError(f"actions: expected a dict {{agent: array ({ACTION_SIZE},)}}, got {type(actions).__name__}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: no action for agent(s) {missing} (every live agent acts each step)")
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            raise ValueError(f"actions: unknown agent(s) {unknown} (the live agents are {self.agents})")
        rows = []
        for agent in self.agents:
            try:
                a = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"actions[{agent!r}]: not a numeric array ({err})") from None
            if a.shape != (ACTION_SIZE,):
                raise ValueError(f"actions[{agent!r}]: shape {a.shape}, expected ({ACTION_SIZE},) "
                                 "(one normalised setpoint in [-1, 1])")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"actions[{agent!r}]: non-finite value(s) {a.tolist()} (NaN or inf)")
            rows.append(a)
        return np.stack(rows).astype(self._action_dtype)

    def _per_agent(self, obs) -> dict:
        obs = np.asarray(obs, np.float32)
        return {a: obs[i].copy() for i, a in enumerate(self.possible_agents)}

    def _infos(self, info, terminated: bool) -> dict:
        success = bool(info["success"])
        common = {"success": success, "failed": terminated and not success, "timeout": bool(info["timeout"]),
                  "target_held": bool(info["target_held"]), "touching": bool(info["touching"]),
                  "episode_length": int(info["episode_length"])}
        return {a: {"terms": {k: float(v[i]) for k, v in info["terms"].items()},
                    "failures": {k: bool(v) for k, v in info["failures"].items()},
                    **common, "episode_return": float(info["episode_return"][i])}
                for i, a in enumerate(self.possible_agents)}

    def _render_rgb(self) -> np.ndarray:
        env = self.capture_env
        phys = jax.device_get(self._state.sim.phys)
        uav = np.asarray(phys.body_pos)[list(env.quad_bodies)]
        knots = np.asarray(phys.point_pos)[list(env.knot_points)]
        target = np.asarray(phys.body_pos)[env.target_body]
        if self._figure is None:   # off-screen, outside pyplot: no window, no global state
            self._figure = Figure(figsize=(8, 4), dpi=80)
            FigureCanvasAgg(self._figure)
        fig = self._figure
        fig.clear()
        for k, (i, j, label) in enumerate(((0, 1, "y"), (0, 2, "z"))):
            ax = fig.add_subplot(1, 2, k + 1)
            ax.scatter(knots[:, i], knots[:, j], s=4, c="0.5", label="net knots")
            ax.scatter(uav[:, i], uav[:, j], s=30, c="C0", label="UAVs")
            ax.add_patch(Circle((target[i], target[j]), env.target_radius, color="C3", label="target"))
            ax.set_xlabel("x [m]")
            ax.set_ylabel(f"{label} [m]")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title("top view" if label == "y" else "side view")
        fig.axes[0].legend(loc="best", fontsize="small")
        fig.canvas.draw()
        return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected an int, got {type(seed).__name__}")
    if not 0 <= seed < SEED_LIMIT:
        raise ValueError(f"seed: {seed} is outside [0, 2**32)")
    return int(seed)
