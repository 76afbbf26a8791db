"""Record one episode of the capture environment, for plots, animations and debugging.

    record = record_episode(env, params, policy, key)
    record.trajectory      # sim.Trajectory on the policy-step grid, the format simulate() returns
    record.rewards         # (length, n_agents), and every term, flag and action per step

:func:`episode_rollout` is the pure part (the episode runner,
:func:`mysim_jax.tasks.runner.rollout`, over ``env.max_steps`` policy steps, saving every
step; jit it, vmap it); :func:`record_episode` jits it, runs it and
cuts the rows at the end of the first episode on the host.

**The terminal state is the one before the reset.** The episode is stepped without
auto-reset (the environment's ``step_env``), so the state saved after its last step is its terminal
state, not the next episode's reset.

**Keys.** ``record_episode(env, params, policy, key, index)`` draws episode ``index`` of
an evaluation seeded with ``key`` exactly as :func:`~mysim_jax.tasks.evaluate.run_episodes`
does (:func:`~mysim_jax.tasks.runner.episode_keys`): the same draws, and the same
states up to floating-point rounding, which differs between compiled programs. Contact is
chaotic: once the target touches the net, that rounding grows (millimetres within a few
steps) and the replay can end differently from the batched episode (as two batched runs
of different batch sizes can).

**Rows.** The trajectory has ``length + 1`` rows: the reset state at ``t = 0`` and the
state after every policy step, the last one at ``t = length · policy_dt``.
Accelerations are evaluated at the saved states with the actuator inputs the
controller holds from there (as :func:`~mysim_jax.driver.simulate` does): at a state
inside the episode, under the setpoint of the action taken from it; at the last state,
under the last action's setpoint (it is held there when the episode ends).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.config.env import FAILURES, REWARD_TERMS
from mysim_jax.control.setpoint import setpoint_from_action
from mysim_jax.io.trajectory import trajectory_columns
from mysim_jax import sim as sim_pipeline
from mysim_jax.sim import Trajectory
from mysim_jax.tasks.runner import episode_keys, numbered_keys, rollout
from mysim_jax.tuning.tracking import motor_columns, reference_columns


def held_accelerations(env, sim_params, sim, actions):
    """Accelerations of the sim state ``sim`` with the inputs the controller holds from
    there under the setpoint of ``actions`` (one state; vmap over rows)."""
    scene = env.scene
    setpoint = setpoint_from_action(scene, sim_params, env.clean_actions(actions, sim.phys.body_pos.dtype))
    held = sim_pipeline.step_updates(scene, sim_params, sim, setpoint)[0]
    return sim_pipeline.held_accelerations(scene, sim_params, sim.phys, held)


def _step_row(step, aux=None) -> dict:
    """:func:`episode_rollout`'s row of one policy step (its docstring)."""
    info = step.info
    return {"sim": step.next_state.sim, "actions": step.actions, "reward": step.reward, "terms": info["terms"],
            "success": info["success"], "failures": jnp.stack([info["failures"][f] for f in FAILURES]),
            "timeout": info["timeout"], "target_held": info["target_held"], "touching": info["touching"], "done": info["done"],
            "returns": info["episode_return"]}


def episode_rollout(env, params, policy, key, index=0):
    """``max_steps`` policy steps of episode ``index`` drawn from ``key`` (pure; module
    docstring).

    Returns ``(first, sim_params, rows)``: the reset sim state, the first episode's
    physics parameters, and per-step stacked ``rows`` (leading axis ``max_steps``):
    ``sim`` (the state after the step, before any reset), ``actions`` (as the policy
    gave them), ``reward``, ``terms`` (weighted, per agent),
    ``success``, ``failures``, ``timeout``, ``target_held``, ``touching``, ``done``, ``returns``
    (the episode's return so far, per agent). The environment does not reset
    (``step_env``): rows after the first ``done`` step on from the ended episode's
    state, and :func:`record_episode` drops them.
    """
    k_reset, _, _ = episode_keys(key, index, 0)
    obs, start = env.reset(k_reset, params)
    sim_params = env.episode_params(params, start.episode)
    _, rows = rollout(env, params, policy, obs, start, jnp.arange(env.max_steps), keys=numbered_keys(key, index),
                      record=_step_row, auto_reset=False)
    return start.sim, sim_params, rows


@dataclass
class EpisodeRecord:
    """One episode on the policy-step grid (host arrays; module docstring)."""

    trajectory: Trajectory          # length + 1 rows; controller memory included (motor columns)
    sim_params: object              # the episode's physics parameters (Params, NumPy leaves)
    actions: np.ndarray             # (length, n_agents, 3) as the policy gave them
    rewards: np.ndarray             # (length, n_agents)
    terms: dict[str, np.ndarray]    # term -> (length, n_agents), weighted
    target_held: np.ndarray         # (length,) bool, the target held after the step
    touching: np.ndarray            # (length,) bool
    success: bool
    failures: dict[str, bool]       # name -> flagged on the last step
    timeout: bool
    returns: np.ndarray             # (n_agents,) the episode's return

    @property
    def length(self) -> int:
        return len(self.rewards)

    @property
    def outcome(self) -> str:
        """``success``, the first failure flagged (FAILURES order), or ``timeout``."""
        if self.success:
            return "success"
        return next((f for f in FAILURES if self.failures[f]), "timeout")


def record_episode(env, params, policy, key, index: int = 0) -> EpisodeRecord:
    """Run episode ``index`` drawn from ``key`` (module docstring) to its first ``done`` and
    keep its states up to and including the terminal, pre-reset one."""
    first, sim_params, rows = jax.jit(lambda p, k: episode_rollout(env, p, policy, k, index))(params, key)
    first, sim_params, rows = jax.tree.map(np.asarray, (first, sim_params, rows))
    done = np.flatnonzero(rows["done"])
    if done.size == 0:       # the time limit ends every episode within max_steps
        raise RuntimeError(f"record_episode: no episode ended within max_steps = {env.max_steps}")
    n = int(done[0]) + 1

    def cut(a):
        return a[:n]

    states = jax.tree.map(lambda a, b: np.concatenate([a[None], b[:n]]), first, rows["sim"])
    # row k's acceleration under the action taken from it; the last row under the last action
    held_actions = np.concatenate([rows["actions"][:n], rows["actions"][n - 1:n]])
    acc = jax.jit(jax.vmap(lambda p, s, a: held_accelerations(env, p, s, a), in_axes=(None, 0, 0)))(
        sim_params, states, held_actions)
    acc = jax.tree.map(np.asarray, acc)
    failures = rows["failures"][n - 1]
    return EpisodeRecord(
        trajectory=Trajectory(time=states.time, phys=states.phys, acc=acc, controller=states.controller,
                              effects=states.effects or None),
        sim_params=sim_params, actions=cut(rows["actions"]), rewards=cut(rows["reward"]),
        terms={t: cut(rows["terms"][t]) for t in REWARD_TERMS}, target_held=cut(rows["target_held"]),
        touching=cut(rows["touching"]), success=bool(rows["success"][n - 1]),
        failures={f: bool(failures[i]) for i, f in enumerate(FAILURES)}, timeout=bool(rows["timeout"][n - 1]),
        returns=rows["returns"][n - 1])


def record_columns(env, record: EpisodeRecord) -> dict[str, np.ndarray]:
    """The ``trajectory.csv`` columns ``scripts/simulate.py`` writes (states, then the
    controller's reference and motor columns) for a recorded episode."""
    traj = record.trajectory
    columns = trajectory_columns(env.scene, traj)
    columns.update(reference_columns(env.scene, record.sim_params, traj.time))
    columns.update(motor_columns(env.scene, traj.controller))
    return columns


def step_columns(env, record: EpisodeRecord) -> dict[str, np.ndarray]:
    """Per policy step of a recorded episode: ``time`` (at the end of the step), every
    agent's reward, every weighted term (mean over agents), ``target_held`` and ``touching``."""
    columns = {"time": np.asarray(record.trajectory.time[1:])}
    for i, agent in enumerate(env.agents):
        columns[f"reward_{agent}"] = record.rewards[:, i]
    for t in REWARD_TERMS:
        columns[f"term_{t}"] = record.terms[t].mean(axis=1)
    columns["target_held"] = record.target_held.astype(int)
    columns["touching"] = record.touching.astype(int)
    return columns
