"""The capture scene as a multi-agent environment, in the gymnax / JaxMARL style.

    env, params = make_env(config)                 # a SceneConfig with net:, target:, env:
    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, actions, params)

As in gymnax, ``env.step_env(key, state, actions, params)`` is one step that returns the
state it reached even when the episode ends, and ``step`` (the same arguments, results of
the same structure) is ``step_env`` followed by the reset of an episode that ended
(**Episode end**). All are pure and written for **one** environment: batch with ``jax.vmap`` (over keys,
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
(:attr:`CaptureEnv.observation_noise`; the ranges' :class:`ObservationNoise` then has no effect). With ``env.perception`` the team flies
on estimates: the UAVs' positions and velocities and the target's carry correlated
estimation errors (first-order Gauss-Markov, :class:`PerceptionErrors` in the state), in
the observations and in what the scripted team sees (:meth:`CaptureEnv.estimates`), at the
levels of ``EnvParams.perception`` (:class:`PerceptionLevels`).
``info["global_state"]`` ``(state_size,)`` is the noise-free state for a centralised critic: every UAV's absolute
state, the target's, the net centre's, the true catch point relative to the formation's
centre and the time to it, the fraction left.

**Rewards** ``(n_agents,)``: potential-based shaping, the effort cost and the outcome
(:mod:`mysim_jax.tasks.rewards`): ``F = γ Φ(s') − Φ(s)`` with ``Φ`` the weighted potential
terms of the state (kept in ``EnvState.potential``; 0 in a state that ends the episode)
and ``γ`` = ``EnvParams.discount`` (the file's ``env.discount``, or ``make_env(config,
discount=)``'s, which a trainer sets to its own discount); ``info["terms"]`` holds every weighted term ``(n_agents,)``
(a shaping term's share of ``F`` for the potential terms), and they sum to the reward.

**Episode end.** ``terminated`` on success (the target held at every policy step over
``success.hold_time``, from its first held step: the measure of
:func:`~mysim_jax.tasks.outcome.capture_outcome` on the policy-step grid)
or any failure (:data:`~mysim_jax.config.env.FAILURES`); ``truncated`` when the
time limit is reached without either. ``info`` flags which (``success``,
``failures[name]``, ``timeout``; ``missed`` when the target reached the ground, ``crashed``
for any other failure) and carries the episode's return and length. On either,
``step`` resets the environment (auto-reset; ``step_env`` does not): the returned ``obs``, ``state`` and
``info["global_state"]`` are the new episode's first; ``info`` describes the episode that
ended, with its last observation, global state and state in ``info["final_obs"]``,
``info["final_global_state"]`` and ``info["final_state"]`` (the first two equal to ``obs`` and ``info["global_state"]`` on other
steps). A step that succeeds reports no failure (``info["failed"]`` is their union).

**Randomisation** per episode, from the reset key: the target's spawn (``target.spawn``)
and everything in ``env.randomize`` and ``env.noise`` (:class:`Episode`).
"""

from __future__ import annotations

from mysim_jax.tasks.capture.env import CaptureEnv
from mysim_jax.tasks.capture.make import line_contact_radius, make_env
from mysim_jax.tasks.capture.observations import CATCH_FEATURES, CATCH_LENGTH_SCALE, CATCH_TIME_SCALE
from mysim_jax.tasks.capture.randomisation import TARGET_DIFFICULTY, scaled_target_ranges
from mysim_jax.tasks.capture.types import (Episode, EnvParams, EnvState, GaussMarkovLevel, ObservationNoise,
                                           PerceptionErrors, PerceptionLevels, Ranges)

__all__ = ["CATCH_FEATURES", "CATCH_LENGTH_SCALE", "CATCH_TIME_SCALE", "TARGET_DIFFICULTY", "CaptureEnv", "EnvParams",
           "EnvState", "Episode", "GaussMarkovLevel", "ObservationNoise", "PerceptionErrors", "PerceptionLevels",
           "Ranges", "line_contact_radius", "make_env", "scaled_target_ranges"]
