"""The capture environment's static structure (:class:`CaptureEnv`, hashable) and its
functional API: ``reset``, ``step`` with auto-reset and ``step_env`` without, the action
checks, and the scripted and random baselines' actions. The environment's other jobs are
its mixins: the per-episode draws (:mod:`.randomisation`), the estimation errors
(:mod:`.perception_errors`), the observations (:mod:`.observations`) and the rewards and
episode ends (:mod:`.verdict`). The package docstring (:mod:`mysim_jax.tasks.capture`) describes the API."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.control.setpoint import setpoint_from_action
from mysim_jax.effects.target import spawn_target
from mysim_jax.sim import step as sim_step
from mysim_jax.tasks.capture.observations import CATCH_FEATURES, ObservationsMixin
from mysim_jax.tasks.capture.perception_errors import PerceptionErrorsMixin
from mysim_jax.tasks.capture.randomisation import RandomisationMixin
from mysim_jax.tasks.capture.types import EnvParams, EnvState
from mysim_jax.tasks.capture.verdict import VerdictMixin


@dataclass(frozen=True)
class CaptureEnv(VerdictMixin, ObservationsMixin, PerceptionErrorsMixin, RandomisationMixin):
    """Static structure of the environment (hashable; see :mod:`mysim_jax.tasks.capture`)."""

    scene: object
    n_agents: int
    agents: tuple[str, ...]              # UAV body names
    quad_bodies: tuple[int, ...]
    target_body: int
    target_radius: float
    line_radius: float                   # [m] the lines as the target touches them (line_contact_radius)
    knot_points: tuple[int, ...]         # every knot's point index
    border_points: tuple[int, ...]       # border knots in order around the net
    tether_markers: tuple[int, ...]      # marker index of every tether attachment
    line_nodes_a: tuple[int, ...]        # node indices of the net's line segments
    line_nodes_b: tuple[int, ...]
    slots: tuple[tuple[float, float, float], ...]   # (n_agents, 3) horizontal start offsets
    control_steps: int                   # control periods per policy step
    max_steps: int                       # policy steps per episode
    policy_dt: float                     # s
    success: object                      # SuccessConfig
    failure: object                      # FailureConfig
    scales: object                       # RewardScales
    randomized_wind: bool
    scripted: object                     # the scripted team (ScriptedTeam)
    falling: bool = True                 # the target falls (else it is maneuvering)
    target_drag_per_mass: float = 0.0    # 1/m, nominal k / m of the target: what the team assumes
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)   # m/s^2, world
    perception: bool = False             # the team flies on estimates (levels: EnvParams.perception)
    observation_noise: bool = True       # env.noise has a nonzero range (else no noise is drawn)
    scene_name: str = ""                 # the scene file's name: (recorded with a trained policy)
    level: str = "full"                  # the scene's fidelity level (recorded with a trained policy)
    thrust_loss: bool = False            # env.randomize.thrust_loss: one UAV's motor fault per episode
    observe_top_thrust: bool = False     # env.observe_top_thrust: every UAV's top-thrust fraction observed
    fault_failsafe: str = "none"         # env.fault_failsafe: none, faulty_uav or team

    # --- sizes ------------------------------------------------------------------------
    @property
    def obs_size(self) -> int:
        motors = self.n_agents if self.observe_top_thrust else 0
        return 13 + 6 + 6 + 6 * (self.n_agents - 1) + CATCH_FEATURES + self.n_agents + 1 + motors

    @property
    def state_size(self) -> int:
        motors = self.n_agents if self.observe_top_thrust else 0
        return 13 * self.n_agents + 6 + 6 + CATCH_FEATURES + 1 + motors

    @property
    def action_shape(self) -> tuple[int, int]:
        return (self.n_agents, 3)

    # --- the functional API -----------------------------------------------------------
    def reset(self, key, params: EnvParams):
        """``(obs, state)``: a fresh episode drawn from ``key``."""
        state = self._reset_state(key, params)
        obs = self._observe(jax.random.fold_in(key, 1), state, params)
        return obs, state

    def step(self, key, state: EnvState, actions, params: EnvParams):
        """``(obs, state, reward, terminated, truncated, info)``: :meth:`step_env`, then the
        reset of an episode that ended (auto-reset, package docstring): its ``obs``,
        ``state`` and ``info["global_state"]`` are then the new episode's first, and
        ``info["final_obs"]``, ``info["final_global_state"]`` and ``info["final_state"]``
        the ended episode's last."""
        obs, after, reward, terminated, truncated, info = self.step_env(key, state, actions, params)
        done = info["done"]
        key_reset, key_obs = jax.random.split(key)
        fresh = self._reset_state(key_reset, params)
        state = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, after)
        obs = jnp.where(done, self._observe(key_obs, state, params), obs)
        info["global_state"] = jnp.where(done, self.global_state(state), info["final_global_state"])
        return obs, state, reward, terminated, truncated, info

    def step_env(self, key, state: EnvState, actions, params: EnvParams):
        """``(obs, state, reward, terminated, truncated, info)`` of one policy step without
        the reset: the state the step reached even when the episode ends (``info`` as in
        :meth:`step`, its ``final_*`` entries equal to the returned values), and no reset's
        code in the traced program. For callers that start episodes themselves
        (:class:`mysim_jax.tasks.evaluate.Evaluator`); :meth:`step` resets from here."""
        dtype = state.sim.phys.body_pos.dtype
        nan = ~jnp.isfinite(self.check_actions(actions))
        actions = self.clean_actions(actions, dtype)
        sim_params = self.episode_params(params, state.episode)
        if self.thrust_loss and self.fault_failsafe != "none":
            actions = self.failsafe(actions, state)
        setpoint = setpoint_from_action(self.scene, sim_params, actions)
        if self.thrust_loss:
            sim_params = self.faulted(sim_params, state.episode, state.steps)

        def control_period(_, s):
            return sim_step(self.scene, sim_params, s, setpoint)

        with jax.named_scope("physics"):
            sim = jax.lax.fori_loop(0, self.control_steps, control_period, state.sim)

        with jax.named_scope("rewards"):
            v = self._judge(state, sim, sim_params, params, dtype)
        held_time, succeeded, failures, steps = v.held_time, v.succeeded, v.failures, v.steps
        crashed, missed, failed, terminated, timeout = v.crashed, v.missed, v.failed, v.terminated, v.timeout
        flags, touched, potential, weighted, reward = v.flags, v.touched, v.potential, v.weighted, v.reward
        returns = state.returns + reward

        done = terminated | timeout
        info = {
            "terms": weighted,
            "success": succeeded,
            "failed": failed,
            "crashed": crashed,
            "missed": missed,
            "failures": failures,
            "timeout": timeout,
            "target_held": flags.held,
            "touching": flags.touching,
            "action_nan": jnp.any(nan),
            "episode_return": returns,
            "episode_length": steps,
            "done": done,
        }
        if sim.contact is not None:
            # control periods of this team step that fell back to all sphere-capsule pairs,
            # and that began with a contact the broad phase had not chosen (must stay 0)
            before, now = state.sim.contact, sim.contact
            info["broad_phase_overflow"] = now.overflow - before.overflow
            info["broad_phase_missed"] = now.missed - before.missed
        errors = (self._step_errors(jax.random.fold_in(key, 2), state.perception, params, dtype, state.sim, sim)
                  if self.perception else state.perception)
        after = EnvState(sim=sim, episode=state.episode, steps=steps, target_held=flags.held, held_time=held_time,
                         touched=touched, returns=returns, potential=potential, perception=errors)
        # the key's second half draws the observation's noise (step resets from its first)
        _, key_obs = jax.random.split(key)
        obs = self._observe(key_obs, after, params)
        info["final_obs"], info["final_state"] = obs, after
        info["final_global_state"] = info["global_state"] = self.global_state(after)
        return obs, after, reward, terminated, timeout, info

    # --- pieces ---------------------------------------------------------------------
    def check_actions(self, actions):
        """Trace-time check of the action's shape (one environment)."""
        actions = jnp.asarray(actions)
        if actions.shape != self.action_shape:
            raise ValueError(f"actions: shape {tuple(actions.shape)}, expected {self.action_shape} "
                             f"(one normalised setpoint in [-1, 1] per UAV {list(self.agents)}; one environment, "
                             "vmap for a batch)")
        if not (jnp.issubdtype(actions.dtype, jnp.floating) or jnp.issubdtype(actions.dtype, jnp.integer)):
            raise ValueError(f"actions: dtype {actions.dtype}, expected a real (float) array")
        return actions

    def clean_actions(self, actions, dtype):
        """Actions as :meth:`step` applies them: shape checked, NaN components set to 0,
        then clipped to ``[-1, 1]``."""
        actions = self.check_actions(actions)
        return jnp.clip(jnp.where(jnp.isfinite(actions), actions.astype(dtype), 0.0), -1.0, 1.0)

    def failsafe(self, actions, state):
        """``actions`` ``(n_agents, 3)`` (velocity setpoints, normalised) after the motor-fault
        failsafe (``env.fault_failsafe``): the vertical component of the faulty UAV's
        (``faulty_uav``) or every UAV's (``team``) floored at 0 from the policy step its
        fault starts on."""
        weak = self.top_thrust_fractions(state.episode, state.steps, actions.dtype) < 1.0
        if self.fault_failsafe == "team":
            weak = jnp.broadcast_to(jnp.any(weak), weak.shape)
        return actions.at[:, 2].set(jnp.where(weak, jnp.maximum(actions[:, 2], 0.0), actions[:, 2]))

    def _reset_state(self, key, params: EnvParams) -> EnvState:
        k_episode, k_spawn = jax.random.split(key)
        episode = self.draw_episode(k_episode, params.ranges)
        sim_params = self.episode_params(params, episode)
        sim = spawn_target(self.scene, sim_params, params.start, k_spawn)
        dtype = sim.phys.body_pos.dtype
        errors = self._draw_errors(jax.random.fold_in(key, 5), params, dtype, sim) if self.perception else None
        snap = self.snapshot(sim, sim_params)
        flags = self.flags(snap)
        potential = self.potential(snap, flags, flags.touching, sim_params, params)
        return EnvState(sim=sim, episode=episode, steps=jnp.zeros((), jnp.int32), target_held=jnp.zeros((), bool),
                        held_time=jnp.zeros((), dtype), touched=flags.touching,
                        returns=jnp.zeros((self.n_agents,), dtype), potential=potential, perception=errors)

    # --- baselines --------------------------------------------------------------------
    def scripted_actions(self, state: EnvState, params: EnvParams):
        """The scripted intercept team's actions ``(n_agents, 3)``
        (:mod:`mysim_jax.tasks.scripted`: with position setpoints the point of the flyable
        box, with velocity setpoints the velocity team's command over ``max_speed``). The team sees the
        true state, or under ``env.perception`` the estimates (:meth:`estimates`), without
        the observation noise."""
        sim_params = self.episode_params(params, state.episode)
        sim = state.sim
        if state.perception is not None:
            quads = np.asarray(self.quad_bodies, dtype=np.int32)
            pos, vel, tpos, tvel = self.estimates(state, params)
            phys = sim.phys
            phys = phys.replace(body_pos=phys.body_pos.at[quads].set(pos).at[self.target_body].set(tpos),
                                body_vel=phys.body_vel.at[quads].set(vel).at[self.target_body].set(tvel))
            sim = sim.replace(phys=phys)
        sp = self.scripted(self.scene, sim_params, sim)
        cp = sim_params.controller
        if self.scene.quadrotor.setpoint_mode == "velocity":
            # the velocity team (scripted.VelocityTeam) commands velocities
            return jnp.clip(sp.velocity / cp.max_speed[:, None], -1.0, 1.0)
        return jnp.clip(2.0 * (sp.position - cp.box_low) / (cp.box_high - cp.box_low) - 1.0, -1.0, 1.0)

    def random_actions(self, key):
        """Uniform actions in ``[-1, 1]`` ``(n_agents, 3)``."""
        return jax.random.uniform(key, self.action_shape, minval=-1.0, maxval=1.0)
