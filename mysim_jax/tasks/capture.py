"""The capture scene as a multi-agent environment, in the gymnax / JaxMARL style.

    env, params = make_env(config)                 # a SceneConfig with net:, target:, env:
    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, actions, params)

Both are pure and written for **one** environment: batch with ``jax.vmap`` (over keys,
states and actions; ``params`` shared or batched too), and jit once around a whole
rollout. ``env`` is a frozen, hashable dataclass (static); ``params`` an
:class:`EnvParams` pytree (traced: reward weights, randomisation ranges and perception
error levels can be vmapped or changed without recompiling).

**Time.** One ``step`` is one policy period ``1 / env.policy_rate``: the action is turned
into a setpoint held for ``control_steps`` control periods (``sim.dt``), in each of
which the cascaded PID runs once and the physics takes its sub-steps. An episode lasts
at most ``sim.t_end``.

**Actions** ``(n_agents, 3)`` in ``[-1, 1]``: one normalised setpoint per UAV
(:func:`~mysim_jax.control.setpoint.setpoint_from_action`: in ``position`` mode a point
of the flyable box, in ``velocity`` mode a fraction of ``max_speed``). Values outside
``[-1, 1]`` are clipped. A NaN action component is replaced by 0 (the box's centre in
position mode, hover in velocity mode) and flagged in ``info["action_nan"]``: inside jit
nothing can raise; the PettingZoo wrapper rejects NaN actions before they get here. A
wrong shape is a ValueError when the step is traced.

**Observations** ``(n_agents, obs_size)``, per agent (world frame, float): its own
position, velocity, attitude quaternion and body rate; the target's position and velocity
relative to it; the net centre's (mean knot) position and velocity relative to it; every
teammate's position and velocity relative to it; the predicted **catch point**
relative to its own slot (where it must fly for the net's centre to meet the target: the
catch point plus its slot offset minus its position, in units of ``CATCH_LENGTH_SCALE``)
and the time to it (in ``CATCH_TIME_SCALE``), from its own measurement of the target
(:meth:`CaptureEnv.catch_point`: the drag-aware fall of a falling target to the net
centre's height; a maneuvering target's position); its one-hot id; the fraction of the
episode left. Own and target measurements carry Gaussian noise (``env.noise``, standard
deviations drawn per episode), independent per agent; a file whose ``env.noise`` ranges are
all zero (the default) makes an environment without the noise's draws in its programs
(:attr:`CaptureEnv.observation_noise`; ``EnvParams.ranges.noise`` then has no effect). With ``env.perception`` the team flies
on estimates: the UAVs' positions and velocities and the target's carry correlated
estimation errors (first-order Gauss-Markov, :class:`PerceptionErrors` in the state), in
the observations and in what the scripted team sees (:meth:`CaptureEnv.estimates`).
``info["global_state"]`` ``(state_size,)`` is the noise-free state for a centralised critic: every UAV's absolute
state, the target's, the net centre's, the true catch point relative to the formation's
centre and the time to it, the fraction left.

**Rewards** ``(n_agents,)``: potential-based shaping, the effort cost and the outcome
(:mod:`mysim_jax.tasks.rewards`): ``F = γ Φ(s') − Φ(s)`` with ``Φ`` the weighted potential
terms of the state (kept in ``EnvState.potential``; 0 in a state that ends the episode)
and ``γ`` = ``env.discount``; ``info["terms"]`` holds every weighted term ``(n_agents,)``
(a shaping term's share of ``F`` for the potential terms), and they sum to the reward.

**Episode end.** ``terminated`` on success (the target held at every policy step over
``success.hold_time``, from its first held step: the measure of
:func:`~mysim_jax.tasks.outcome.capture_outcome` on the policy-step grid)
or any failure (:data:`~mysim_jax.config.env.FAILURES`); ``truncated`` when the
time limit is reached without either. ``info`` flags which (``success``,
``failures[name]``, ``timeout``; ``missed`` when the target reached the ground, ``crashed``
for any other failure) and carries the episode's return and length. On either,
the environment resets inside ``step`` (auto-reset): the returned ``obs``, ``state`` and
``info["global_state"]`` are the new episode's first; ``info`` describes the episode that
ended, with its last observation, global state and state in ``info["final_obs"]``,
``info["final_global_state"]`` and ``info["final_state"]`` (the first two equal to ``obs`` and ``info["global_state"]`` on other
steps). A step that succeeds reports no failure (``info["failed"]`` is their union).

**Randomisation** per episode, from the reset key: the target's spawn (``target.spawn``)
and everything in ``env.randomize`` and ``env.noise`` (:class:`Episode`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.build import build
from mysim_jax.config.capture import TeamConfig
from mysim_jax.config.env import (COST_TERMS, CRASHES, MISSES, OUTCOME_TERMS, REWARD_TERMS,
                                  SHAPING_TERMS, NoiseConfig, dropout_per_step)
from mysim_jax.control.setpoint import setpoint_from_action
from mysim_jax.core import rng
from mysim_jax.core.config_base import ConfigError
from mysim_jax.core.types import Params, State
from mysim_jax.dynamics.quaternion import quat_rotate
from mysim_jax.effects.target import spawn_target
from mysim_jax.sim import step as sim_step
from mysim_jax.tasks.intercept import CatchPoint, predict_catch
from mysim_jax.tasks.outcome import border_knots
from mysim_jax.tasks.rewards import Snapshot, checks, cost_terms, hold_reached, outcome_terms, potential_terms
from mysim_jax.tasks.scripted import team_policy


@struct.dataclass
class Episode:
    """What is drawn per episode (besides the target's spawn, which lives in the sim state)."""

    target_mass: jnp.ndarray      # () kg
    uav_mass_scale: jnp.ndarray   # () -
    wind_force: jnp.ndarray       # (3,) N on every UAV, world
    flee_acceleration: jnp.ndarray  # () m/s^2
    jink_acceleration: jnp.ndarray  # () m/s^2
    max_speed: jnp.ndarray        # () m/s
    noise: jnp.ndarray            # (4,) sigma of UAV position [m], UAV velocity [m/s], target position, velocity
    # env.randomize.thrust_loss only (None otherwise: no draws, the same state as without the effect)
    thrust_fraction: jnp.ndarray | None = None   # () of the faulty UAV's nominal maximum thrust
    thrust_loss_time: jnp.ndarray | None = None  # () s, when the fault starts
    thrust_loss_uav: jnp.ndarray | None = None   # () in [0, n_agents): the faulty UAV is its integer part


@struct.dataclass
class Ranges:
    """Per-episode randomisation ranges ``low``/``high`` of every :class:`Episode` field."""

    low: Episode
    high: Episode


@struct.dataclass
class EnvParams:
    """Traced environment parameters (vmap or change them without recompiling)."""

    sim: Params                   # the scene's nominal physics parameters
    start: State                  # the nominal first state (the target is placed by the reset)
    weights: jnp.ndarray          # (n_terms,) reward weights, REWARD_TERMS order, >= 0
    discount: jnp.ndarray         # () γ of the potential-based shaping
    ranges: Ranges
    # (4, 2) (sigma, rho per policy step) of the estimation errors of UAV position [m], UAV
    # velocity [m/s], target position, target velocity (env.perception; rho = exp(-policy_dt
    # / correlation_time)); zeros when the team sees true states
    perception: jnp.ndarray
    target_delay: jnp.ndarray     # () the target estimate's latency over the policy period, in [0, 1]
    # (2,) per policy step: the probability of losing the target estimate while it is seen,
    # and of regaining it while lost (env.perception.target_dropout); zeros: never lost
    target_dropout: jnp.ndarray


@struct.dataclass
class PerceptionErrors:
    """The current estimation errors (estimate minus truth) when the team flies on
    estimates (``env.perception``); each a first-order Gauss-Markov process per axis. With
    the target's true state one policy step ago, which the estimate's latency interpolates
    towards (at an episode's start: its first state), and whether the target estimate is
    lost (``perception.target_dropout``) with the last one the team had."""

    uav_pos: jnp.ndarray          # (n_agents, 3) m, each UAV's own position estimate
    uav_vel: jnp.ndarray          # (n_agents, 3) m/s
    target_pos: jnp.ndarray       # (3,) m, the team's fused target estimate
    target_vel: jnp.ndarray       # (3,) m/s
    target_pos_before: jnp.ndarray   # (3,) m, true, one policy step ago
    target_vel_before: jnp.ndarray   # (3,) m/s
    target_lost: jnp.ndarray         # () bool, the target estimate is lost (it coasts)
    target_last_pos: jnp.ndarray     # (3,) m, the target estimate when last seen
    target_last_vel: jnp.ndarray     # (3,) m/s
    target_lost_steps: jnp.ndarray   # () int32, policy steps since it was last seen


@struct.dataclass
class EnvState:
    """State of one environment."""

    sim: State
    episode: Episode
    steps: jnp.ndarray            # () int32, policy steps taken this episode
    held: jnp.ndarray             # () bool, the target was held after the last step
    held_time: jnp.ndarray        # () s from the first held step of the current hold to the last
    touched: jnp.ndarray          # () bool, the target has touched the net this episode
    returns: jnp.ndarray          # (n_agents,) sum of rewards this episode
    potential: jnp.ndarray        # (n_shaping_terms, n_agents) weighted potential terms of this state
    perception: PerceptionErrors | None = None   # None unless the team flies on estimates


class _Verdict(NamedTuple):
    """One step's outcome and reward (:meth:`CaptureEnv._judge`)."""

    flags: object
    held_time: jnp.ndarray
    succeeded: jnp.ndarray
    failures: dict
    crashed: jnp.ndarray
    missed: jnp.ndarray
    failed: jnp.ndarray
    steps: jnp.ndarray
    terminated: jnp.ndarray
    timeout: jnp.ndarray
    touched: jnp.ndarray
    potential: jnp.ndarray
    weighted: dict
    reward: jnp.ndarray


@dataclass(frozen=True)
class CaptureEnv:
    """Static structure of the environment (hashable; see the module docstring)."""

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

    # --- sizes ------------------------------------------------------------------------
    @property
    def obs_size(self) -> int:
        return 13 + 6 + 6 + 6 * (self.n_agents - 1) + CATCH_FEATURES + self.n_agents + 1

    @property
    def state_size(self) -> int:
        return 13 * self.n_agents + 6 + 6 + CATCH_FEATURES + 1

    @property
    def action_shape(self) -> tuple[int, int]:
        return (self.n_agents, 3)

    # --- the functional API -----------------------------------------------------------
    def reset(self, key, params: EnvParams):
        """``(obs, state)``: a fresh episode drawn from ``key``."""
        state = self._reset_state(key, params)
        obs = self._observe(jax.random.fold_in(key, 1), state, params)
        return obs, state

    def _judge(self, state: EnvState, sim, sim_params, params: EnvParams, dtype) -> "_Verdict":
        """The step's outcome and reward from the state it reached (``sim``)."""
        snap = self.snapshot(sim, sim_params)
        flags = self.flags(snap)
        # measured as capture_outcome measures it: from the first held sample, so a
        # hold of k consecutive held steps lasts (k - 1) policy periods
        held_time = jnp.where(flags.held & state.held, state.held_time + self.policy_dt, 0.0).astype(dtype)
        succeeded = flags.held & hold_reached(held_time, self.success.hold_time)
        # a step that succeeds is not a failure (the flags are exclusive in info)
        failures = {k: v & ~succeeded for k, v in flags.failures.items()}
        crashed = jnp.any(jnp.stack([failures[k] for k in CRASHES]))
        missed = jnp.any(jnp.stack([failures[k] for k in MISSES])) & ~crashed
        failed = crashed | missed
        steps = state.steps + 1
        terminated = succeeded | failed
        timeout = (steps >= self.max_steps) & ~terminated
        touched = state.touched | flags.touching
        potential = self.potential(snap, flags, touched, sim_params, params)
        # F = γ Φ(s') − Φ(s), with Φ = 0 in a state that ends the episode
        shaping = params.discount.astype(dtype) * jnp.where(terminated, 0.0, potential) - state.potential
        weighted = {k: shaping[i] for i, k in enumerate(SHAPING_TERMS)}
        costs = cost_terms(snap)
        outcomes = outcome_terms(self.n_agents, dtype, succeeded=succeeded, missed=missed, crashed=crashed)
        w = self.weights(params, dtype)
        weighted.update({k: w[k] * costs[k] for k in COST_TERMS})
        weighted.update({k: w[k] * outcomes[k] for k in OUTCOME_TERMS})
        weighted = {k: weighted[k] for k in REWARD_TERMS}
        return _Verdict(flags=flags, held_time=held_time, succeeded=succeeded, failures=failures, crashed=crashed,
                        missed=missed, failed=failed, steps=steps, terminated=terminated, timeout=timeout,
                        touched=touched, potential=potential, weighted=weighted, reward=sum(weighted.values()))

    def step(self, key, state: EnvState, actions, params: EnvParams, auto_reset: bool = True):
        """``(obs, state, reward, terminated, truncated, info)`` (module docstring).
        ``auto_reset=False`` (a Python bool) returns the state after the step even when the
        episode ends, and leaves the reset's code out of the traced program: for callers
        that start episodes themselves (:class:`mysim_jax.tasks.evaluate.Evaluator`)."""
        dtype = state.sim.phys.body_pos.dtype
        nan = ~jnp.isfinite(self.check_actions(actions))
        actions = self.clean_actions(actions, dtype)
        sim_params = self.episode_params(params, state.episode)
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
            "held": flags.held,
            "touching": flags.touching,
            "action_nan": jnp.any(nan),
            "episode_return": returns,
            "episode_length": steps,
            "done": done,
        }
        if "capsule_broad_phase" in sim.effects:
            # control periods of this team step that fell back to all sphere-capsule pairs,
            # and that began with a contact the broad phase had not chosen (must stay 0)
            before, now = state.sim.effects["capsule_broad_phase"], sim.effects["capsule_broad_phase"]
            info["broad_phase_overflow"] = now.overflow - before.overflow
            info["broad_phase_missed"] = now.missed - before.missed
        errors = (self._step_errors(jax.random.fold_in(key, 2), state.perception, params, dtype, state.sim, sim)
                  if self.perception else state.perception)
        after = EnvState(sim=sim, episode=state.episode, steps=steps, held=flags.held, held_time=held_time,
                         touched=touched, returns=returns, potential=potential, perception=errors)
        key_reset, key_obs = jax.random.split(key)
        if not auto_reset:
            obs = self._observe(key_obs, after, params)
            info["final_obs"], info["final_state"] = obs, after
            info["final_global_state"] = info["global_state"] = self.global_state(after)
            return obs, after, reward, terminated, timeout, info
        fresh = self._reset_state(key_reset, params)
        # the episode's last observation (before the reset), e.g. to bootstrap a value
        # on truncation
        info["final_obs"] = self._observe(key_obs, after, params)
        info["final_global_state"] = self.global_state(after)
        info["final_state"] = after
        state = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, after)
        obs = jnp.where(done, self._observe(key_obs, state, params), info["final_obs"])
        info["global_state"] = jnp.where(done, self.global_state(state), info["final_global_state"])
        return obs, state, reward, terminated, timeout, info

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

    def draw_episode(self, key, ranges: Ranges) -> Episode:
        leaves_low, treedef = jax.tree.flatten(ranges.low)
        leaves_high = jax.tree.leaves(ranges.high)
        keys = jax.random.split(key, len(leaves_low))
        # one draw for every field (the scene's dtype), each from its own key
        drawn = rng.uniform_each(keys, [lo.shape for lo in leaves_low], leaves_low[0].dtype, leaves_low, leaves_high)
        return jax.tree.unflatten(treedef, drawn)

    def episode_params(self, params: EnvParams, ep: Episode) -> Params:
        """The physics parameters of one episode: the nominal ones with its draws."""
        sim = params.sim
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        body_mass = sim.body_mass.at[quads].multiply(ep.uav_mass_scale)
        inertia = sim.body_inertia.at[quads].multiply(ep.uav_mass_scale)
        t = self.target_body
        ratio = ep.target_mass / sim.body_mass[t]
        body_mass = body_mass.at[t].set(ep.target_mass)
        inertia = inertia.at[t].multiply(ratio)
        tp = sim.effects["target"].replace(flee_acceleration=ep.flee_acceleration,
                                           jink_acceleration=ep.jink_acceleration, max_speed=ep.max_speed)
        sim = sim.replace(body_mass=body_mass, body_inertia=inertia, effects={**sim.effects, "target": tp})
        if self.randomized_wind:
            qp = sim.quadrotor
            sim = sim.replace(quadrotor=qp.replace(wind_force=qp.wind_force + ep.wind_force[None, :]))
        return sim

    def faulted(self, sim_params: Params, ep: Episode, steps) -> Params:
        """``sim_params`` with the episode's motor fault (``env.randomize.thrust_loss``) in
        force for the policy step that starts after ``steps`` steps: from the first step
        at or after the fault's time, the faulty UAV's rotor top speed is √fraction of the
        nominal (its maximum thrust ``fraction`` of the nominal)."""
        qp = sim_params.quadrotor
        dtype = qp.omega_max.dtype
        started = steps.astype(dtype) * self.policy_dt >= ep.thrust_loss_time
        faulty = jnp.arange(self.n_agents) == jnp.minimum(jnp.floor(ep.thrust_loss_uav), self.n_agents - 1)
        scale = jnp.where(started & faulty, jnp.sqrt(ep.thrust_fraction), 1.0).astype(dtype)
        return sim_params.replace(quadrotor=qp.replace(omega_max=qp.omega_max * scale))

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
        return EnvState(sim=sim, episode=episode, steps=jnp.zeros((), jnp.int32), held=jnp.zeros((), bool),
                        held_time=jnp.zeros((), dtype), touched=flags.touching,
                        returns=jnp.zeros((self.n_agents,), dtype), potential=potential, perception=errors)

    # --- rewards ----------------------------------------------------------------------
    def weights(self, params: EnvParams, dtype) -> dict:
        """Every term's weight ``name -> ()`` (REWARD_TERMS)."""
        return {k: params.weights[i].astype(dtype) for i, k in enumerate(REWARD_TERMS)}

    def _gravity(self, dtype):
        return jnp.asarray(self.gravity, dtype)

    def catch_point(self, target_pos, target_vel, net_z, gravity) -> CatchPoint:
        """Where and when the target meets the net's height ``net_z`` (m), as the team can
        predict it: a falling target's drag-aware fall with the nominal drag per mass
        (:func:`~mysim_jax.tasks.intercept.predict_catch`); a maneuvering target's current
        position (it does not fall; ``time`` 0)."""
        if self.falling:
            return predict_catch(target_pos, target_vel, net_z, gravity, self.target_drag_per_mass)
        return CatchPoint(point=target_pos, time=jnp.zeros((), target_pos.dtype), velocity=target_vel,
                          crossed=jnp.ones((), bool))

    def potential(self, snap: Snapshot, flags, touched, sim_params: Params, params: EnvParams):
        """The weighted potential terms ``(n_shaping_terms, n_agents)`` of one state
        (SHAPING_TERMS order; :func:`~mysim_jax.tasks.rewards.potential_terms`), from its
        true state: the catch point is predicted from the target's true position and
        velocity and the net centre's height."""
        dtype = snap.uav_pos.dtype
        net_z = jnp.mean(snap.knot_pos[:, 2])
        catch = self.catch_point(snap.target_pos, snap.target_vel, net_z, self._gravity(dtype))
        terms = potential_terms(snap, flags, catch_point=catch.point, slots=jnp.asarray(self.slots, dtype),
                                scales=self.scales, touched=touched)
        w = self.weights(params, dtype)
        return jnp.stack([w[k] * terms[k] for k in SHAPING_TERMS])

    # --- flying on estimates (env.perception) -----------------------------------------
    def _error_shapes(self):
        n = self.n_agents
        return {"uav_pos": (n, 3), "uav_vel": (n, 3), "target_pos": (3,), "target_vel": (3,)}

    def _target_now(self, sim: State):
        phys = sim.phys
        return {"target_pos_before": phys.body_pos[self.target_body],
                "target_vel_before": phys.body_vel[self.target_body]}

    def _draw_errors(self, key, params: EnvParams, dtype, sim: State) -> PerceptionErrors:
        """Errors drawn from their stationary distributions (an episode's first state ``sim``)."""
        keys = jax.random.split(key, 4)
        sigma = params.perception[:, 0].astype(dtype)
        shapes = self._error_shapes()
        xi = rng.normal_each(keys, list(shapes.values()), dtype)
        e = {name: sigma[i] * xi[i] for i, name in enumerate(shapes)}
        now = self._target_now(sim)
        return PerceptionErrors(**e, **now, target_lost=jnp.zeros((), bool),
                                target_last_pos=now["target_pos_before"] + e["target_pos"],
                                target_last_vel=now["target_vel_before"] + e["target_vel"],
                                target_lost_steps=jnp.zeros((), jnp.int32))

    def _step_errors(self, key, errors: PerceptionErrors, params: EnvParams, dtype, before: State,
                     after: State) -> PerceptionErrors:
        """One policy period of every Gauss-Markov error: ``e' = rho e + sigma √(1 - rho²) ξ``;
        ``before``: the state the period started from (the target's, for the latency);
        ``after``: the state it ended in. Then one step of the target estimate's losses: lost
        (seen) it is regained (lost) with probability ``params.target_dropout[1]`` (``[0]``);
        while seen, the estimate is remembered, while lost it ages."""
        keys = jax.random.split(key, 4)
        sigma, rho = params.perception[:, 0].astype(dtype), params.perception[:, 1].astype(dtype)
        drive = sigma * jnp.sqrt(jnp.maximum(1.0 - rho * rho, 0.0))
        shapes = self._error_shapes()
        xi = rng.normal_each(keys, list(shapes.values()), dtype)
        new = {name: (rho[i] * getattr(errors, name) + drive[i] * xi[i]).astype(dtype)
               for i, name in enumerate(shapes)}
        u = jax.random.uniform(jax.random.fold_in(key, 7), (), dtype)
        p_lose, p_regain = params.target_dropout[0].astype(dtype), params.target_dropout[1].astype(dtype)
        lost = jnp.where(errors.target_lost, u >= p_regain, u < p_lose)
        fresh = PerceptionErrors(**new, **self._target_now(before), target_lost=lost,
                                 target_last_pos=errors.target_last_pos, target_last_vel=errors.target_last_vel,
                                 target_lost_steps=errors.target_lost_steps)
        tpos, tvel = self._seen_target(after.phys, fresh, params)
        return fresh.replace(target_last_pos=jnp.where(lost, errors.target_last_pos, tpos),
                             target_last_vel=jnp.where(lost, errors.target_last_vel, tvel),
                             target_lost_steps=jnp.where(lost, errors.target_lost_steps + 1, 0))

    def _seen_target(self, phys, e: PerceptionErrors, params: EnvParams):
        """The target estimate when the target is seen: its state of ``params.target_delay``
        of the way back to the last policy step, plus the estimation errors."""
        pos, vel = phys.body_pos[self.target_body], phys.body_vel[self.target_body]
        f = params.target_delay.astype(pos.dtype)
        return (pos + f * (e.target_pos_before - pos) + e.target_pos,
                vel + f * (e.target_vel_before - vel) + e.target_vel)

    def _coasted_target(self, e: PerceptionErrors):
        """The target estimate while lost: the last one coasted over the time since, at its
        velocity (a falling target: under gravity)."""
        t = e.target_lost_steps.astype(e.target_last_pos.dtype) * self.policy_dt
        g = jnp.asarray(self.gravity if self.falling else (0.0, 0.0, 0.0), e.target_last_pos.dtype)
        return e.target_last_pos + e.target_last_vel * t + 0.5 * g * t * t, e.target_last_vel + g * t

    def estimates(self, state: EnvState, params: EnvParams):
        """``(uav_pos (n, 3), uav_vel (n, 3), target_pos (3,), target_vel (3,))`` as the team
        knows them: the true values, plus the estimation errors under ``env.perception``;
        the target's of ``perception.target_latency`` ago (``params.target_delay`` of the
        way back to the previous policy step), coasted from the last one while the target
        estimate is lost (``perception.target_dropout``)."""
        phys = state.sim.phys
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        if state.perception is None:
            return (phys.body_pos[quads], phys.body_vel[quads], phys.body_pos[self.target_body],
                    phys.body_vel[self.target_body])
        e = state.perception
        seen, coasted = self._seen_target(phys, e, params), self._coasted_target(e)
        tpos, tvel = (jnp.where(e.target_lost, c, s) for s, c in zip(seen, coasted))
        return phys.body_pos[quads] + e.uav_pos, phys.body_vel[quads] + e.uav_vel, tpos, tvel

    def snapshot(self, sim: State, sim_params: Params) -> Snapshot:
        phys = sim.phys
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        markers = np.asarray(self.tether_markers, dtype=np.int32)
        body_of = np.asarray(self.scene.marker_body, dtype=np.int32)[markers]
        attach = phys.body_pos[body_of] + quat_rotate(phys.body_quat[body_of], sim_params.marker_pos[markers])
        # every line node is a point mass (knots and line masses)
        a = np.asarray(self.line_nodes_a, dtype=np.int32)
        b = np.asarray(self.line_nodes_b, dtype=np.int32)
        qp = sim_params.quadrotor
        return Snapshot(
            uav_pos=phys.body_pos[quads], uav_vel=phys.body_vel[quads], uav_quat=phys.body_quat[quads],
            uav_angvel=phys.body_angvel[quads],
            rotor_fraction=sim.controller.motor_speed / qp.omega_max[:, None],
            target_pos=phys.body_pos[self.target_body], target_vel=phys.body_vel[self.target_body],
            knot_pos=phys.point_pos[knots], knot_vel=phys.point_vel[knots],
            border=phys.point_pos[np.asarray(self.border_points, dtype=np.int32)], attach=attach,
            line_a=phys.point_pos[a], line_b=phys.point_pos[b],
            entanglement=sim.effects["entanglement"].level if "entanglement" in sim.effects else None)

    def flags(self, snap: Snapshot):
        return checks(snap, target_radius=self.target_radius, line_radius=self.line_radius,
                      contact_margin=self.scales.contact_margin, success=self.success, failure=self.failure)

    def _observe(self, key, state: EnvState, params: EnvParams):
        phys = state.sim.phys
        dtype = phys.body_pos.dtype
        n = self.n_agents
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        sigma = state.episode.noise.astype(dtype)
        est_pos, est_vel, est_tpos, est_tvel = self.estimates(state, params)
        if self.observation_noise:
            xi = rng.normal_each(jax.random.split(key, 4), [(n, 3)] * 4, dtype)
            pos = est_pos + sigma[0] * xi[0]
            vel = est_vel + sigma[1] * xi[1]
            tpos = est_tpos + sigma[2] * xi[2]
            tvel = est_tvel + sigma[3] * xi[3]
        else:   # sigma is 0 in every episode: the same values without the draws' code
            pos, vel, tpos, tvel = (jnp.broadcast_to(x, (n, 3)) for x in (est_pos, est_vel, est_tpos, est_tvel))
        c_net = jnp.mean(phys.point_pos[knots], axis=0)
        v_net = jnp.mean(phys.point_vel[knots], axis=0)
        # each agent's own prediction of the catch point, from its measurement of the target
        gravity = self._gravity(dtype)
        catch = jax.vmap(lambda p, v: self.catch_point(p, v, c_net[2], gravity))(tpos, tvel)
        slots = jnp.asarray(self.slots, dtype)
        to_slot = (catch.point + slots - pos) / CATCH_LENGTH_SCALE
        catch_time = catch.time[:, None] / CATCH_TIME_SCALE
        # teammates j != i, relative to i, in a fixed order per agent
        others = np.asarray([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int32).reshape(n, n - 1)
        mates = jnp.concatenate([est_pos[others] - pos[:, None, :], est_vel[others] - vel[:, None, :]], axis=-1)
        left = 1.0 - state.steps.astype(dtype) / self.max_steps
        obs = jnp.concatenate([
            pos, vel, phys.body_quat[quads], phys.body_angvel[quads],
            tpos - pos, tvel - vel,
            c_net[None, :] - pos, v_net[None, :] - vel,
            mates.reshape(n, 6 * (n - 1)),
            to_slot, catch_time,
            jnp.eye(n, dtype=dtype),
            jnp.broadcast_to(left, (n, 1)),
        ], axis=-1)
        return jnp.where(jnp.isfinite(obs), obs, 0.0)

    def global_state(self, state: EnvState):
        """The noise-free global state ``(state_size,)`` for a centralised critic."""
        phys = state.sim.phys
        dtype = phys.body_pos.dtype
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        uav = jnp.concatenate([phys.body_pos[quads], phys.body_vel[quads], phys.body_quat[quads],
                               phys.body_angvel[quads]], axis=-1).reshape(-1)
        left = 1.0 - state.steps.astype(dtype) / self.max_steps
        c_net = jnp.mean(phys.point_pos[knots], axis=0)
        catch = self.catch_point(phys.body_pos[self.target_body], phys.body_vel[self.target_body], c_net[2],
                                 self._gravity(dtype))
        centre = jnp.mean(phys.body_pos[quads], axis=0)
        out = jnp.concatenate([uav, phys.body_pos[self.target_body], phys.body_vel[self.target_body],
                               c_net, jnp.mean(phys.point_vel[knots], axis=0),
                               (catch.point - centre) / CATCH_LENGTH_SCALE, catch.time[None] / CATCH_TIME_SCALE,
                               left[None]])
        return jnp.where(jnp.isfinite(out), out, 0.0)

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


# the catch-point features of an observation: the catch point relative to the agent's
# slot position (3, in units of CATCH_LENGTH_SCALE) and the time to it (1, in units of
# CATCH_TIME_SCALE)
CATCH_FEATURES = 4
CATCH_LENGTH_SCALE = 2.0    # m
CATCH_TIME_SCALE = 1.0      # s


TARGET_DIFFICULTY = ("max_speed", "jink_acceleration", "flee_acceleration")
"""The episode draws a curriculum scales (:func:`scaled_target_ranges`)."""


def scaled_target_ranges(ranges: Ranges, fraction) -> Ranges:
    """``ranges`` with the low and high ends of the evading target's top speed, jink and
    flee accelerations (:data:`TARGET_DIFFICULTY`) multiplied by ``fraction`` (a training
    curriculum's stage, ``env.curriculum`` of a training file); the other draws unchanged."""
    def scale(episode):
        return episode.replace(**{k: getattr(episode, k) * jnp.asarray(fraction, getattr(episode, k).dtype)
                                  for k in TARGET_DIFFICULTY})

    return Ranges(low=scale(ranges.low), high=scale(ranges.high))


def _ranges(config, dtype, n_agents: int) -> Ranges:
    env, target = config.env, config.target
    r = env.randomize
    prop = target.propulsion_or_default()

    def rng(value, nominal):
        lo, hi = (nominal, nominal) if value is None else (value.low, value.high)
        return jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)

    pairs = {
        "target_mass": rng(r.target_mass, target.mass),
        "uav_mass_scale": rng(r.uav_mass_scale, 1.0),
        "wind_force": (jnp.asarray((0.0, 0.0, 0.0) if r.wind_force is None else r.wind_force.low, dtype),
                       jnp.asarray((0.0, 0.0, 0.0) if r.wind_force is None else r.wind_force.high, dtype)),
        "flee_acceleration": rng(r.flee_acceleration, prop.flee_acceleration if prop else 0.0),
        "jink_acceleration": rng(r.jink_acceleration, prop.jink_acceleration if prop else 0.0),
        "max_speed": rng(r.max_speed, prop.max_speed if prop else 0.0),
        "noise": tuple(jnp.asarray([getattr(getattr(env.noise, f), side) for f in
                                    ("uav_position", "uav_velocity", "target_position", "target_velocity")], dtype)
                       for side in ("low", "high")),
    }
    if r.thrust_loss is not None:
        t = r.thrust_loss
        pairs["thrust_fraction"] = rng(t.fraction, 1.0)
        pairs["thrust_loss_time"] = rng(t.time, 0.0)
        # the faulty UAV: uniform over [0, n_agents), its integer part
        pairs["thrust_loss_uav"] = (jnp.asarray(0.0, dtype), jnp.asarray(n_agents, dtype))
    return Ranges(low=Episode(**{k: v[0] for k, v in pairs.items()}),
                  high=Episode(**{k: v[1] for k, v in pairs.items()}))


def line_contact_radius(scene, params, target_body: int, line_springs, default: float) -> float:
    """Radius [m] of the net's lines as the target touches them, read from the built
    contact scene: the largest capsule radius among the sphere–capsule pairs of the
    target's sphere and the capsules on ``line_springs`` (spring names), or ``default``
    (half the line's diameter) when the scene pairs none. The environment's ``touching``
    check measures the gap from there, so a level that thickens the lines for contact
    counts a touch where its contact acts."""
    cs = scene.contact
    if cs is None or not cs.n_capsule_pairs or target_body not in cs.sphere_body:
        return default
    sphere = len(cs.sphere_point) + cs.sphere_body.index(target_body)
    lines = set(line_springs)
    radius = np.asarray(params.contact.capsule_radius, float)
    radii = [radius[c] for a, c in zip(cs.capsule_pair_sphere, cs.capsule_pair_capsule)
             if a == sphere and cs.capsule_names[c] in lines]
    return float(max(radii)) if radii else default


def make_env(config) -> tuple[CaptureEnv, EnvParams]:
    """The environment of a capture SceneConfig with an ``env:`` block (ValueError
    naming what is missing otherwise)."""
    if config.env is None:
        raise ValueError(f"scene '{config.name}': no env: block (add `env: {{}}` for the defaults)")
    env_cfg, net = config.env, config.net
    scene, params, state = build(config)
    if env_cfg.randomize.wind_force is not None and not scene.quadrotor.has_wind:
        scene = dataclasses.replace(scene, quadrotor=dataclasses.replace(scene.quadrotor, has_wind=True))
    team = team_policy(config.model_copy(update={"team": config.team or _default_team()}), scene)
    quads = [q.body for q in config.quadrotors]
    bodies = {b.name: b for b in config.bodies}
    start = np.asarray([bodies[q].pos for q in quads], float)
    slots = start - start.mean(axis=0)
    slots[:, 2] = 0.0
    knots = [net.knot_name(i, j) for i in range(net.knots) for j in range(net.knots)]
    line_names = [n for n in scene.spring_names if n.startswith((f"{net.name}_h", f"{net.name}_v"))]
    line_index = [scene.spring_names.index(n) for n in line_names]
    n_points = scene.n_points
    a = [scene.spring_node_a[i] for i in line_index]
    b = [scene.spring_node_b[i] for i in line_index]
    if max(a + b) >= n_points:
        raise ValueError("net lines must join point masses")
    tethers = [scene.marker_names.index(f"{u}.{net.name}_tether") for u in net.tethers.uavs] if net.tethers else []
    if not tethers:
        raise ValueError("env: the net has no tethers (net.tethers), so nothing carries it")
    control_steps = int(round(1.0 / env_cfg.policy_rate / config.sim.dt))
    max_steps = int(round(config.sim.t_end / (control_steps * config.sim.dt)))
    env = CaptureEnv(
        scene=scene, n_agents=len(quads), agents=tuple(quads),
        quad_bodies=tuple(scene.body_names.index(q) for q in quads),
        target_body=scene.body_names.index(config.target.name), target_radius=float(config.target.radius),
        line_radius=line_contact_radius(scene, params, scene.body_names.index(config.target.name), line_names,
                                        0.5 * float(net.line.diameter)),
        knot_points=tuple(scene.point_names.index(k) for k in knots),
        border_points=tuple(scene.point_names.index(k) for k in border_knots(net)),
        tether_markers=tuple(tethers), line_nodes_a=tuple(a), line_nodes_b=tuple(b),
        slots=tuple(map(tuple, slots.tolist())), control_steps=control_steps, max_steps=max_steps,
        policy_dt=control_steps * config.sim.dt, success=env_cfg.success, failure=env_cfg.failure,
        scales=env_cfg.reward_scales, randomized_wind=env_cfg.randomize.wind_force is not None, scripted=team,
        thrust_loss=env_cfg.randomize.thrust_loss is not None,
        falling=config.target.behaviour == "falling",
        target_drag_per_mass=float(config.target.drag_constant / config.target.mass),
        gravity=tuple(float(g) for g in config.gravity),
        perception=env_cfg.perception is not None, scene_name=config.name, level=config.level,
        observation_noise=any(getattr(env_cfg.noise, f).high > 0.0 for f in NoiseConfig.model_fields))
    weights = env_cfg.weights()
    env_params = EnvParams(sim=params, start=state,
                           weights=jnp.asarray([weights[k] for k in REWARD_TERMS], scene.dtype),
                           discount=jnp.asarray(env_cfg.discount, scene.dtype),
                           ranges=_ranges(config, scene.dtype, len(quads)),
                           perception=jnp.asarray(_perception(env_cfg.perception, control_steps * config.sim.dt),
                                                  scene.dtype),
                           target_delay=jnp.asarray(_target_delay(env_cfg.perception, control_steps * config.sim.dt),
                                                    scene.dtype),
                           target_dropout=jnp.asarray(_target_dropout(env_cfg.perception,
                                                                      control_steps * config.sim.dt), scene.dtype))
    return env, env_params


def _perception(config, policy_dt: float) -> list:
    """``[(sigma, rho), ...]`` of ``env.perception``'s four errors per policy step (zeros
    when there is none)."""
    if config is None:
        return [(0.0, 0.0)] * 4
    out = []
    for name in ("uav_position", "uav_velocity", "target_position", "target_velocity"):
        gm = getattr(config, name)
        tau = gm.correlation_time
        out.append((float(gm.sigma), float(np.exp(-policy_dt / tau)) if tau > 0 else 0.0))
    return out


def _target_delay(config, policy_dt: float) -> float:
    """``env.perception.target_latency`` over the policy period (0 without perception)."""
    if config is None or config.target_latency == 0.0:
        return 0.0
    if config.target_latency > policy_dt * (1 + 1e-9):
        raise ConfigError(f"env.perception.target_latency {config.target_latency:g} s is more than the policy period "
                          f"{policy_dt:g} s (control steps x sim.dt): lower it or the policy rate")
    return min(config.target_latency / policy_dt, 1.0)


def _target_dropout(config, policy_dt: float) -> tuple[float, float]:
    """``(p_lose, p_regain)`` per policy step of ``env.perception.target_dropout`` ((0, 0):
    never lost)."""
    if config is None or config.target_dropout is None:
        return 0.0, 0.0
    try:
        return dropout_per_step(config.target_dropout, policy_dt, "env.perception.target_dropout")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _default_team():
    return TeamConfig(policy="scripted")
