"""MAPPO in JAX: a policy shared by every agent, a centralised critic, PPO's update.

    trainer = Trainer(config.algo, env, env_params)
    state = trainer.init(key)
    for _ in range(config.algo.num_iterations):
        state, metrics = trainer.iteration(state)      # one jitted call

or ``state, metrics = trainer.iterations(state, n)`` (n iterations as one ``lax.scan``);
the whole run as a pure function of a key is :func:`mysim_jax.mappo.algorithm.make_train`.

**Networks** (flax, :mod:`mysim_jax.mappo.networks`): the actor maps one agent's observation (its one-hot id is part of
it, so one network serves every UAV) to the mean of a diagonal Gaussian over its action;
the log standard deviations are free parameters, one per action dimension. Sampled
actions are clipped to ``[-1, 1]`` by the environment; the log-probabilities are those of
the unclipped samples (as CleanRL and PureJaxRL do). The critic sees the environment's
noise-free global state and the agent's one-hot id and returns that agent's value: MAPPO's
centralised critic, one value per agent because rewards are per agent. With
``residual``, the environment receives the scripted team's action plus the policy's
(residual policy learning: the untrained policy flies the scripted intercept, and training
learns corrections to it); the log-probabilities are those of the residual.

**Iteration** (:meth:`Trainer.iteration`, one ``jax.jit``): a ``lax.scan`` of
``num_steps`` policy steps of ``num_envs`` environments (the environment step batched as
``algo.batching`` says: :func:`mysim_jax.core.batching.vmap`, batch axis last, in cache-sized
blocks, on a CPU; ``jax.vmap`` on a GPU or TPU; :attr:`Trainer.env_batching`), then GAE, then
``update_epochs`` passes over ``num_minibatches`` shuffled minibatches of team transitions
with Adam on ``policy loss + vf_coef * value loss − ent_coef * entropy``, the gradient's
global norm clipped to ``max_grad_norm``, the learning rate constant or decaying linearly to
zero over the run. Observations and states are normalised by running statistics (updated
after each iteration's update, so a rollout and its update use the same normalisation), and
value targets by MAPPO's ValueNorm. An episode cut by the time limit is bootstrapped with the
value of its last state (``info["final_global_state"]``), or with ``algo.bootstrap_time_limit:
false`` ended there like any other episode.

Everything the next iteration needs is in :class:`TrainerState` (environments included),
so a checkpoint of it resumes a run exactly.

**Several devices** (``mesh``, a :func:`mysim_jax.core.parallel.env_mesh`): the environments'
leaves of the state (``env_state``, ``obs``, ``global_state``) are split over the mesh's
``"env"`` axis and everything else is replicated; the iteration is the same jitted program,
partitioned by XLA from those shardings. Each device steps its own block of environments
(the rollout, where the time goes); the rollout's buffers are then gathered and every
device runs the same update on the whole batch (global minibatches, as on one device), so
every device holds the same parameters. The result equals one device's to float round-off
(``tests/test_parallel.py``). ``num_envs`` must be divisible by the number of devices.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import NamedSharding, PartitionSpec as P

from mysim_jax.core import batching, parallel
from mysim_jax.mappo.config import network_memory_bytes
from mysim_jax.mappo.curriculum import CurriculumState
from mysim_jax.mappo.networks import Actor, Critic, deterministic_policy_fn
from mysim_jax.mappo.losses import (RunningStats, gae, gaussian_entropy, gaussian_log_prob, normalize_advantages,
                                    policy_loss, value_loss)

@struct.dataclass
class TrainerState:
    """Everything a training run carries from one iteration to the next."""

    params: dict                 # {"actor": ..., "critic": ...}
    opt_state: Any
    obs_stats: RunningStats      # (obs_size,)
    state_stats: RunningStats    # (state_size,)
    ret_stats: RunningStats      # () value targets
    env_state: Any               # (num_envs, ...) environment states
    obs: jnp.ndarray             # (num_envs, n_agents, obs_size)
    global_state: jnp.ndarray    # (num_envs, state_size)
    key: jnp.ndarray
    iteration: jnp.ndarray       # () int32, iterations done
    anchor: dict                 # the policy the anchor pulls towards (policy_arrays layout; algo.init: bc, policy)
    best: dict                   # the best policy so far by model selection (policy_arrays layout)
    best_score: jnp.ndarray      # (2,) its (successes, mean return) on the selection episodes; -inf: none yet
    best_iteration: jnp.ndarray  # () int32, the iteration it was taken after (-1: none yet)
    ranges: Any                  # the episode ranges new training episodes are drawn from (a capture
                                 # environment's Ranges; None for an environment without them)
    curriculum: CurriculumState  # where the curriculum stands (env.curriculum; zeros without one)


@struct.dataclass
class Transition:
    obs: jnp.ndarray          # (B, A, O) normalised as the actor saw it
    critic_in: jnp.ndarray    # (B, A, S + A)
    action: jnp.ndarray       # (B, A, act)
    log_prob: jnp.ndarray     # (B, A)
    value: jnp.ndarray        # (B, A) value (return units)
    reward: jnp.ndarray       # (B, A) with the time-limit bootstrap added
    done: jnp.ndarray         # (B,)
    raw_obs: jnp.ndarray      # (B, A, O)
    raw_state: jnp.ndarray    # (B, S)
    success: jnp.ndarray      # (B,) episode ended in success at this step
    episode_return: jnp.ndarray   # (B,) mean over agents of the ended episode's return
    episode_length: jnp.ndarray   # (B,)
    step_reward: jnp.ndarray      # (B,) mean over agents of the environment's reward


def _policy_arrays(params: dict, obs_stats: RunningStats) -> dict:
    return {"actor": params["actor"], "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}


def _step_info(info) -> dict:
    keep = ("success", "done", "episode_return", "episode_length", "final_global_state", "global_state")
    return {k: info[k] for k in keep}


@dataclass(frozen=True, eq=False)        # hashed and compared by identity (it holds arrays)
class Trainer:
    """MAPPO on ``env`` (module docstring). ``config`` an :class:`~mysim_jax.mappo.config.AlgoConfig`."""

    config: Any
    env: Any
    env_params: Any
    mesh: Any = None          # a jax.sharding.Mesh with the axis "env" (None: one device)
    curriculum: Any = None    # a mysim_jax.mappo.curriculum.Curriculum over env_params.ranges (None: none)

    def __post_init__(self):
        if self.curriculum is not None and getattr(self.env_params, "ranges", None) is None:
            raise ValueError("a curriculum scales episode ranges: this environment has none")
        if self.mesh is not None and self.config.num_envs % self.mesh.size:
            raise ValueError(f"algo.num_envs {self.config.num_envs} is not divisible by the {self.mesh.size} devices "
                             "the environments are split over (run.devices)")

    # what the settings above determine, built once on first use (frozen: nothing changes after)
    @cached_property
    def actor(self) -> Actor:
        return Actor(self.env.action_shape[1], tuple(self.config.hidden), self.config.activation, self.config.init_std)

    @cached_property
    def critic(self) -> Critic:
        return Critic(tuple(self.config.hidden), self.config.activation)

    @cached_property
    def tx(self) -> optax.GradientTransformation:
        return self._optimizer()

    @cached_property
    def _iteration_jit(self):
        return jax.jit(self._iteration)

    @cached_property
    def _init(self):
        return jax.jit(self._init_state)

    @cached_property
    def _knobs(self) -> dict:
        return self._make_knobs()

    @cached_property
    def _one_state(self):
        """One environment's state, shapes and dtypes only."""
        return jax.eval_shape(lambda k: self.env.reset(k, self.env_params)[1], jax.random.PRNGKey(0))

    @cached_property
    def block(self) -> int | None:
        """The environments :func:`~mysim_jax.core.batching.vmap` steps at a time (None: all)."""
        return batching.chunk_for(self._one_state)

    @cached_property
    def env_batching(self) -> str:
        """How the rollout batches the environment step, ``"batch_last"`` or ``"vmap"``:
        ``algo.batching``, with ``auto`` resolved for the platform of the devices the
        trainer runs on (:func:`~mysim_jax.core.batching.resolve_batching`)."""
        platform = None if self.mesh is None else self.mesh.devices.flat[0].platform
        return batching.resolve_batching(self.config.batching, platform)

    def batch(self, fun, in_axes=0):
        """``fun`` (written for one environment) batched over environments as this trainer
        batches its rollout (:attr:`env_batching`; batch-last in blocks of :attr:`block`)."""
        kind = self.env_batching
        return batching.batch(fun, kind, in_axes, chunk=self.block if kind == "batch_last" else None)

    def memory_needs(self) -> dict:
        """An estimate of the memory one iteration holds, ``{part: (bytes, the fields that
        size it)}``, from the sizes alone (no compile): the networks
        (:func:`~mysim_jax.mappo.config.network_memory_bytes`); the environment states
        (three per environment: the carried state, the stepped one and the fresh reset it
        may be replaced by; one state's bytes from ``jax.eval_shape`` of the reset); and the
        rollout's buffers (a :class:`Transition` per environment and step, float32, plus
        the advantages and value targets computed from it). XLA's temporaries inside the
        step come on top: this is a lower bound, for refusing sizes that cannot fit."""
        c = self.config
        n, act = self.env.action_shape
        obs, state = self.env.obs_size, self.env.state_size
        # Transition: obs, raw_obs (n, O); critic_in (n, S + n); action (n, act); log_prob,
        # value, reward (n); raw_state (S); episode_return, episode_length, step_reward; then
        # advantage and target (n); done and success are booleans (a byte each)
        per_step = 4 * (n * (2 * obs + state + n + act + 3) + state + 3 + 2 * n) + 2
        env_state = batching.tree_nbytes(self._one_state)
        return {"networks": (network_memory_bytes(c), "algo.hidden"),
                "environment states": (3 * c.num_envs * env_state, "algo.num_envs"),
                "rollout buffers": (c.num_envs * c.num_steps * per_step, "algo.num_envs x algo.num_steps")}

    def iteration(self, ts: "TrainerState"):
        """One iteration (module docstring): ``(new state, metrics)``, one jitted call. The
        KL limit and the anchor's schedule are arguments of the compiled program, not
        constants in it: trainers that differ only in ``target_kl``, ``bc.anchor_coef``,
        ``bc.anchor_iterations`` or ``bc.critic_warmup`` run the same program."""
        return self._iteration_jit(self.place(ts), self._knobs)

    def iterations(self, ts: "TrainerState", n, length: int | None = None):
        """``n`` iterations as one ``lax.scan``: ``(state after them, metrics)``, each metric
        stacked ``(n,)``. With ``length``, the scan has ``length`` steps of which the first
        ``n`` (then an array, at most ``length``) are iterations and the rest leave the state
        as it is (their metrics zeros): one compiled program runs any number of iterations
        up to ``length``, which is how the run loop (:func:`mysim_jax.mappo.run.train_run`)
        advances between checkpoints and selections. Traceable (no placement, no host
        transfer): :func:`~mysim_jax.mappo.algorithm.make_train` scans a whole run with it,
        and ``jax.vmap`` maps it over seeds (``n`` shared)."""
        knobs = self.knobs()
        if length is None:
            return jax.lax.scan(lambda carry, _: self._iteration(carry, knobs), ts, None, length=n)
        idle = jax.tree.map(lambda m: jnp.zeros(m.shape, m.dtype), jax.eval_shape(self._iteration, ts, knobs)[1])

        def body(carry, i):
            return jax.lax.cond(i < n, lambda c: self._iteration(c, knobs), lambda c: (c, idle), carry)

        return jax.lax.scan(body, ts, jnp.arange(length))

    @cached_property
    def _advance_jit(self):
        return {False: jax.jit(self.iterations, static_argnums=2),
                True: jax.jit(jax.vmap(self.iterations, in_axes=(0, None, None)), static_argnums=2)}

    def advance(self, ts: "TrainerState", n: int, length: int, seeds: bool = False):
        """:meth:`iterations` ``(ts, n, length)`` jitted, on the trainer's devices; with
        ``seeds``, ``ts`` holds one run per seed along a leading axis (vmapped, one program)."""
        if seeds and self.mesh is not None:
            raise ValueError("several seeds in one program run on one device (no mesh)")
        return self._advance_jit[seeds](ts if seeds else self.place(ts), jnp.int32(n), length)

    def place(self, ts: "TrainerState") -> "TrainerState":
        """``ts`` on the trainer's devices: the environments' leaves split over the mesh, the
        rest replicated (unchanged without a mesh; arrays already in place are not copied)."""
        if self.mesh is None:
            return ts

        if jax.process_count() == 1:
            envs = parallel.shard_envs((ts.env_state, ts.obs, ts.global_state), self.mesh)
            rest = parallel.replicate(ts.replace(env_state=None, obs=None, global_state=None), self.mesh)
        else:
            # several processes: a leaf not yet in place (computed by this process alone, e.g.
            # behaviour cloning's networks or model selection's best policy, the same values
            # in every process) goes through the host; leaves in place stay where they are
            split, whole = (NamedSharding(self.mesh, spec) for spec in (P(parallel.ENV_AXIS), P()))

            def put(sharding):
                def one(x):
                    if isinstance(x, jax.Array) and x.sharding.is_equivalent_to(sharding, x.ndim):
                        return x
                    return jax.device_put(np.asarray(x), sharding)
                return one
            envs = jax.tree.map(put(split), (ts.env_state, ts.obs, ts.global_state))
            rest = jax.tree.map(put(whole), ts.replace(env_state=None, obs=None, global_state=None))
        return rest.replace(env_state=envs[0], obs=envs[1], global_state=envs[2])

    def knobs(self) -> dict:
        """The settings the iteration takes as arguments (:meth:`_make_knobs`, made once)."""
        return self._knobs

    def _make_knobs(self) -> dict:
        """The settings the iteration takes as arguments (float32 scalars): the KL past which
        an iteration's remaining minibatches are skipped (inf without ``target_kl``), and
        the anchor schedule's weight, length and critic warm-up (0 without ``init: bc``).
        NumPy scalars, not JAX arrays: made on first use, which may be inside a trace
        (:meth:`iterations` under ``jax.jit``), where a JAX array would be a tracer that
        the cache keeps after the trace ends."""
        c = self.config
        anchor = self.uses_anchor
        return {"kl_stop": np.float32(np.inf if c.target_kl is None else 1.5 * c.target_kl),
                "anchor_coef": np.float32(c.bc.anchor_coef if anchor else 0.0),
                "anchor_iterations": np.float32(c.bc.anchor_iterations),
                "critic_warmup": np.float32(self.critic_warmup)}

    def with_episode_ranges(self, ts: "TrainerState", ranges) -> "TrainerState":
        """``ts`` drawing its new training episodes from ``ranges`` (a capture environment's
        :class:`~mysim_jax.tasks.capture.Ranges`, as :func:`~mysim_jax.tasks.capture.scaled_target_ranges`
        gives) from the next iteration on: a field of the state, so nothing recompiles and a
        checkpoint keeps it. Model selection and evaluation keep ``env_params``' own."""
        if ts.ranges is None:
            raise ValueError("with_episode_ranges: this environment has no episode ranges")
        if self.curriculum is not None:
            raise ValueError("with_episode_ranges: this trainer's curriculum sets the ranges every iteration")
        if jax.tree.structure(ranges) != jax.tree.structure(ts.ranges):
            raise ValueError("with_episode_ranges: ranges of another environment")
        ranges = jax.tree.map(lambda new, o: jnp.asarray(new, o.dtype).reshape(o.shape), ranges, ts.ranges)
        return ts.replace(ranges=ranges)

    # --- pieces ----------------------------------------------------------------------
    def _schedule(self):
        """The learning rate as a function of the number of gradient steps taken."""
        c = self.config
        if c.lr_schedule == "linear":
            return optax.linear_schedule(c.lr, 0.0, c.num_updates)
        return optax.constant_schedule(c.lr)

    def _optimizer(self):
        c = self.config
        return optax.chain(optax.clip_by_global_norm(c.max_grad_norm), optax.adam(self._schedule(), eps=1e-5))

    def learning_rate(self, iteration) -> float:
        """The learning rate of the first update of iteration ``iteration`` (0-based)."""
        c = self.config
        return float(self._schedule()(iteration * c.update_epochs * c.num_minibatches))

    @property
    def n_agents(self) -> int:
        return self.env.action_shape[0]

    def critic_input(self, state_n):
        """``(..., S)`` normalised global states -> ``(..., A, S + A)`` with every agent's id."""
        a = self.n_agents
        eye = jnp.eye(a, dtype=state_n.dtype)
        tiled = jnp.broadcast_to(state_n[..., None, :], state_n.shape[:-1] + (a, state_n.shape[-1]))
        ids = jnp.broadcast_to(eye, state_n.shape[:-1] + (a, a))
        return jnp.concatenate([tiled, ids], axis=-1)

    def _norm_obs(self, stats, x):
        return stats.normalize(x) if self.config.normalize_obs else x

    def _values(self, params, ret_stats, state_stats, states):
        """Values in return units ``(..., A)`` of raw global states ``(..., S)``."""
        v = self.critic.apply(params["critic"], self.critic_input(self._norm_obs(state_stats, states)))
        return ret_stats.denormalize(v) if self.config.value_norm else v

    def _env_step(self, ranges=None):
        env, env_params = self.env, self.env_params
        if ranges is not None:
            env_params = env_params.replace(ranges=ranges)

        residual = self.config.residual

        def one(key, state, action):
            if residual:
                action = action + env.scripted_actions(state, env_params)
            obs, state, reward, terminated, truncated, info = env.step(key, state, action, env_params)
            return obs, state, reward, terminated, truncated, _step_info(info)

        return self.batch(one)

    # --- init ------------------------------------------------------------------------
    def _init_state(self, key) -> TrainerState:
        c, env = self.config, self.env
        k_actor, k_critic, k_env, k_run = jax.random.split(key, 4)
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_env, c.num_envs), self.env_params)
        obs = obs.astype(jnp.float32)
        gstate = jax.vmap(env.global_state)(env_state).astype(jnp.float32)
        params = {"actor": self.actor.init(k_actor, obs[0, 0]),
                  "critic": self.critic.init(k_critic, self.critic_input(gstate[0])[0])}
        obs_stats = RunningStats.create((obs.shape[-1],)).update(obs)
        state_stats = RunningStats.create((gstate.shape[-1],)).update(gstate)
        arrays = _policy_arrays(params, obs_stats)
        state = TrainerState(params=params, opt_state=self.tx.init(params), obs_stats=obs_stats,
                            state_stats=state_stats, ret_stats=RunningStats.create(), env_state=env_state, obs=obs,
                            global_state=gstate, key=k_run, iteration=jnp.int32(0), anchor=arrays, best=arrays,
                            best_score=jnp.full((2,), -jnp.inf, jnp.float32), best_iteration=jnp.int32(-1),
                            ranges=getattr(self.env_params, "ranges", None), curriculum=CurriculumState.start())
        if self.curriculum is not None:       # the first stage, and its episode ranges
            cs = self.curriculum.start()
            return state.replace(curriculum=cs, ranges=self.curriculum.ranges(self.env_params.ranges, cs))
        return state

    def init(self, key) -> TrainerState:
        """A fresh run from ``key``: networks, optimiser, ``num_envs`` reset environments
        (placed on the mesh's devices when there is one)."""
        return self.place(self._init(key))

    # --- one iteration -----------------------------------------------------------------
    def _rollout(self, ts: TrainerState, knobs: dict | None = None):
        c = self.config
        step_batch = self._env_step(ts.ranges)
        params = ts.params

        def one(carry, _):
            env_state, obs, gstate, key = carry
            key, k_act, k_step = jax.random.split(key, 3)
            obs_n = self._norm_obs(ts.obs_stats, obs)
            mean, log_std = self.actor.apply(params["actor"], obs_n)
            action = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape, mean.dtype)
            log_prob = gaussian_log_prob(action, mean, log_std)
            critic_in = self.critic_input(self._norm_obs(ts.state_stats, gstate))
            value = self.critic.apply(params["critic"], critic_in)
            if c.value_norm:
                value = ts.ret_stats.denormalize(value)
            keys = jax.random.split(k_step, c.num_envs)
            obs2, env_state2, reward, _, truncated, info = step_batch(keys, env_state, action)
            reward = reward.astype(jnp.float32)
            if c.bootstrap_time_limit:
                final_value = self._values(params, ts.ret_stats, ts.state_stats,
                                           info["final_global_state"].astype(jnp.float32))
                boot = reward + c.gamma * final_value * truncated[:, None].astype(jnp.float32)
            else:   # the time limit ends the task: nothing follows the last step
                boot = reward
            done = info["done"]
            tr = Transition(obs=obs_n, critic_in=critic_in, action=action, log_prob=log_prob, value=value,
                            reward=boot, done=done, raw_obs=obs, raw_state=gstate,
                            success=info["success"] & done,
                            episode_return=jnp.mean(info["episode_return"], axis=-1).astype(jnp.float32),
                            episode_length=info["episode_length"], step_reward=jnp.mean(reward, axis=-1))
            return (env_state2, obs2.astype(jnp.float32), info["global_state"].astype(jnp.float32), key), tr

        carry = (ts.env_state, ts.obs, ts.global_state, ts.key)
        (env_state, obs, gstate, key), traj = jax.lax.scan(one, carry, None, length=c.num_steps)
        return env_state, obs, gstate, key, traj

    def _loss(self, params, mb, policy_coef, anchor_coef):
        c = self.config
        mean, log_std = self.actor.apply(params["actor"], mb["obs"])
        log_prob = gaussian_log_prob(mb["action"], mean, log_std)
        adv = normalize_advantages(mb["advantage"])
        pl, clip_frac, kl = policy_loss(log_prob, mb["log_prob"], adv, c.clip_eps)
        v = self.critic.apply(params["critic"], mb["critic_in"])
        vl = value_loss(v, mb["old_value"], mb["target"], c.value_clip_eps)
        entropy = jnp.mean(gaussian_entropy(log_std))
        total = policy_coef * (pl - c.ent_coef * entropy) + c.vf_coef * vl
        aux = {"policy_loss": pl, "value_loss": vl, "entropy": entropy, "clip_fraction": clip_frac, "approx_kl": kl}
        if self.uses_anchor:
            anchor = jnp.mean(jnp.sum((mean - mb["anchor_mean"]) ** 2, axis=-1))
            total = total + policy_coef * anchor_coef * anchor
            aux["anchor_loss"] = anchor
        return total, aux

    # --- behaviour cloning and its anchor ----------------------------------------------
    @property
    def uses_anchor(self) -> bool:
        """The run starts from a policy (the clone, or a saved one) and is anchored to it."""
        return self.config.init in ("bc", "policy")

    @property
    def critic_warmup(self) -> int:
        """Iterations at the start that train only the critic."""
        return self.config.bc.critic_warmup if self.uses_anchor else 0

    def schedule(self, iteration, knobs: dict | None = None):
        """``(policy_coef, anchor_coef)`` of iteration ``iteration`` (0-based): the policy is
        held (0) during the critic's warm-up; the anchor decays linearly to 0 over
        ``bc.anchor_iterations`` after it (``knobs``: :meth:`knobs`, by default this
        trainer's)."""
        k = self.knobs() if knobs is None else knobs
        it = jnp.asarray(iteration, jnp.float32)
        warm = k["critic_warmup"]
        policy_coef = jnp.where(it < warm, 0.0, 1.0)
        left = jnp.clip(1.0 - (it - warm) / k["anchor_iterations"], 0.0, 1.0)
        return policy_coef, k["anchor_coef"] * left

    def anchor_means(self, anchor: dict, raw_obs):
        """The anchor policy's action means ``(..., act)`` at raw observations ``(..., obs_size)``."""
        stats = RunningStats(mean=anchor["obs_mean"], var=anchor["obs_var"], count=jnp.asarray(1.0))
        mean, _ = self.actor.apply(anchor["actor"], self._norm_obs(stats, raw_obs))
        return mean

    def _iteration(self, ts: TrainerState, knobs: dict | None = None):
        c = self.config
        knobs = self.knobs() if knobs is None else knobs
        env_state, obs, gstate, key, traj = self._rollout(ts, knobs)
        adv, targets, ret_stats = self._targets(ts, traj, gstate)
        policy_coef, anchor_coef = self.schedule(ts.iteration, knobs)

        def to_critic_units(x):
            return (x - ret_stats.mean) / ret_stats.std if c.value_norm else x

        n = c.batch_size
        data = {
            "obs": traj.obs, "critic_in": traj.critic_in, "action": traj.action, "log_prob": traj.log_prob,
            "advantage": adv, "target": to_critic_units(targets), "old_value": to_critic_units(traj.value),
        }
        if self.uses_anchor:
            data["anchor_mean"] = self.anchor_means(ts.anchor, traj.raw_obs)
        data = jax.tree.map(lambda x: x.reshape((n,) + x.shape[2:]), data)
        kl_stop = knobs["kl_stop"]

        def epoch(carry, k):
            params, opt_state, stopped = carry
            perm = jax.random.permutation(k, n)
            shuffled = jax.tree.map(lambda x: x[perm].reshape((c.num_minibatches, c.minibatch_size) + x.shape[1:]),
                                    data)

            def minibatch(carry, mb):
                params, opt_state, stopped = carry
                (_, aux), grads = jax.value_and_grad(self._loss, has_aux=True)(params, mb, policy_coef, anchor_coef)
                # the KL of the policy before this update: past the limit, this and every
                # later minibatch of the iteration is skipped
                stopped = stopped | (aux["approx_kl"] > kl_stop)
                updates, new_opt_state = self.tx.update(grads, opt_state, params)
                new_params = optax.apply_updates(params, updates)
                params, opt_state = jax.tree.map(lambda old, new: jnp.where(stopped, old, new),
                                                 (params, opt_state), (new_params, new_opt_state))
                aux["grad_norm"] = optax.tree.norm(grads)
                aux["updates_applied"] = (~stopped).astype(jnp.float32)
                return (params, opt_state, stopped), aux

            return jax.lax.scan(minibatch, (params, opt_state, stopped), shuffled)

        key, k_update = jax.random.split(key)
        (params, opt_state, _), aux = jax.lax.scan(epoch, (ts.params, ts.opt_state, jnp.bool_(False)),
                                                   jax.random.split(k_update, c.update_epochs))
        metrics = {k: jnp.mean(v) for k, v in aux.items()}
        metrics.update(policy_coef=policy_coef, anchor_coef=anchor_coef)
        return self._finish(ts, traj, targets, metrics, params=params, opt_state=opt_state, ret_stats=ret_stats,
                            env_state=env_state, obs=obs, global_state=gstate, key=key)

    def _targets(self, ts: TrainerState, traj: Transition, gstate):
        """``(advantages, value targets, value normaliser)`` of a rollout ``traj`` ending at
        the raw global states ``gstate`` (GAE with ``gamma`` and ``gae_lambda``; targets in
        return units, the normaliser updated with them under ``value_norm``)."""
        c = self.config
        last_value = self._values(ts.params, ts.ret_stats, ts.state_stats, gstate)
        dones = jnp.broadcast_to(traj.done[..., None], traj.reward.shape)
        adv, targets = gae(traj.reward, traj.value, dones, last_value, c.gamma, c.gae_lambda)
        ret_stats = ts.ret_stats.update(targets) if c.value_norm else ts.ret_stats
        return adv, targets, ret_stats

    def _finish(self, ts: TrainerState, traj: Transition, targets, metrics: dict, **new):
        """The iteration's end, shared by the algorithms: the state ``ts`` with the fields
        ``new`` (parameters, optimiser, environments, ...), the observation statistics
        updated with the rollout ``traj``, one more iteration and the curriculum's next
        stage; and ``metrics`` completed with the rollout's episodes (return, success,
        length), the critic's explained variance of ``targets`` and the action noise."""
        c = self.config
        params = new["params"]
        frozen = self.uses_anchor and c.bc.freeze_obs_norm   # the actor keeps its start's normalisation
        obs_stats = ts.obs_stats.update(traj.raw_obs) if c.normalize_obs and not frozen else ts.obs_stats
        state_stats = ts.state_stats.update(traj.raw_state) if c.normalize_obs else ts.state_stats

        ended = traj.done.astype(jnp.float32)
        n_ended = jnp.sum(ended)
        var_t = jnp.var(targets)
        metrics = dict(metrics)
        metrics.update({
            "episodes": n_ended,
            "mean_return": jnp.sum(traj.episode_return * ended) / jnp.maximum(n_ended, 1.0),
            "success_rate": jnp.sum(traj.success.astype(jnp.float32)) / jnp.maximum(n_ended, 1.0),
            "mean_length": jnp.sum(traj.episode_length * ended) / jnp.maximum(n_ended, 1.0),
            "step_reward": jnp.mean(traj.step_reward),
            "explained_variance": 1.0 - jnp.var(targets - traj.value) / jnp.maximum(var_t, 1e-8),
            "action_std": jnp.mean(jnp.exp(params["actor"]["params"]["log_std"])),
        })
        new = ts.replace(obs_stats=obs_stats, state_stats=state_stats, iteration=ts.iteration + 1, **new)
        if self.curriculum is not None:
            # the stage this iteration trained in; the next draws from the stage the rule gives
            metrics["curriculum_stage"] = ts.curriculum.stage
            metrics["curriculum_fraction"] = self.curriculum.fraction_of(ts.curriculum)
            rate = jnp.where(n_ended > 0, metrics["success_rate"], jnp.nan)
            cs, _ = self.curriculum.update(ts.curriculum, rate)
            new = new.replace(curriculum=cs, ranges=self.curriculum.ranges(self.env_params.ranges, cs))
        return new, metrics

    # --- the trained policy ------------------------------------------------------------
    def policy_arrays(self, ts: TrainerState) -> dict:
        """What the deterministic policy needs: the actor's parameters and the observation
        statistics (of the current policy; the best one is ``ts.best``)."""
        return _policy_arrays(ts.params, ts.obs_stats)

    def run_policy(self, ts: TrainerState) -> dict:
        """The run's policy: the best by model selection when there has been one, else the
        current one."""
        return jax.tree.map(lambda b, c: jnp.where(ts.best_iteration >= 0, b, c), ts.best, self.policy_arrays(ts))

    def keep_if_best(self, ts: TrainerState, successes: int, mean_return: float) -> TrainerState:
        """``ts`` with its current policy as the best when ``(successes, mean_return)`` beats
        the best score so far (lexicographically)."""
        best_s, best_r = (float(x) for x in jax.device_get(ts.best_score))
        if (successes, mean_return) > (best_s, best_r):
            return ts.replace(best=self.policy_arrays(ts),
                              best_score=jnp.asarray([successes, mean_return], jnp.float32),
                              best_iteration=jnp.asarray(ts.iteration, jnp.int32))
        return ts

    def policy_fn(self):
        """``policy(key, obs, state, params, arrays)``: the deterministic policy with its
        arrays traced (:class:`~mysim_jax.tasks.evaluate.Evaluator`)."""
        return deterministic_policy_fn(self.actor, self.config.normalize_obs,
                                       self.env.scripted_actions if self.config.residual else None)

