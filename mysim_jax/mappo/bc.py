"""Warm starts of PPO: behaviour cloning of the scripted team (``algo.init: bc``), or a
saved policy (``algo.init: policy``, :func:`from_policy`).

    demos = collect(trainer, key)                 # the vmapped environment, scripted team + noise
    state, stats = fit(trainer, state, demos, key)
    state, stats = clone(trainer, state, key)     # collect and fit, with DAgger's rounds
    report(trainer, stats)                        # a JSON-ready dict of the fit (bc.json)

All three are pure functions of their arguments (no host transfer): a training run's start
(:func:`mysim_jax.mappo.algorithm.start`) jits them with the rest, and vmaps them over seeds.

**Demonstrations** (:func:`collect`): ``bc.num_envs`` environments run ``bc.steps`` policy
steps side by side (the episode runner, :func:`mysim_jax.tasks.runner.rollout`, in the
trainer's batch-last layout; each step's key split into the noise's and the
environment's). At every step each environment's scripted action ``a*``
(:meth:`CaptureEnv.scripted_actions`, in the action space) is the label, and the
environment is stepped with ``a* + bc.noise · ξ`` (ξ standard normal): the states a
slightly perturbed scripted team visits, each labelled with what the scripted team would
do there (DART, Laskey et al. 2017), so the clone also learns to recover from
the small errors it will make. Episodes end and reset as in training.

**Fit** (:func:`fit`): the observation statistics are those of the demonstrations; the
actor's mean is fitted to the labels by least squares (Adam, ``bc.epochs`` passes in
shuffled minibatches of ``bc.minibatch_size``). The environments of the last
``bc.holdout`` fraction are held out: their states were never trained on, and the report
gives the fit there (RMSE, R² per action dimension). The exploration standard deviation
is set to ``bc.std``, the anchor (:attr:`TrainerState.anchor`) to the clone, and the
optimiser is reset.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from mysim_jax.mappo.losses import RunningStats
from mysim_jax.mappo.policies import PolicyError, check_trained_on
from mysim_jax.tasks.runner import rollout


@struct.dataclass
class Demonstrations:
    """Scripted-team labels at the states a perturbed scripted team visited."""

    obs: jnp.ndarray          # (steps, envs, n_agents, obs_size), raw observations
    actions: jnp.ndarray      # (steps, envs, n_agents, act), the scripted team's actions there
    success: jnp.ndarray      # (steps, envs) an episode ended in success at this step
    done: jnp.ndarray         # (steps, envs) an episode ended at this step

    @property
    def pairs(self) -> int:
        """Observation-action pairs (one per agent and step)."""
        return int(np.prod(self.obs.shape[:3]))


def collect(trainer, key, arrays=None) -> Demonstrations:
    """The demonstrations of the module docstring for ``trainer``'s environment. With
    ``arrays`` (:meth:`Trainer.policy_arrays` of a clone) the clone flies instead of the
    scripted team (its deterministic action plus the same noise), still labelled with the
    scripted team's action at every state it visits (DAgger)."""
    bc = trainer.config.bc
    env, params = trainer.env, trainer.env_params
    student = None if arrays is None else trainer.policy_fn()

    def one_env(key, state, obs, arrays):
        def pilot(k_noise, obs, state, params):
            teacher = env.scripted_actions(state, params)
            flies = teacher if student is None else student(k_noise, obs, state, params, arrays).astype(teacher.dtype)
            return flies + bc.noise * jax.random.normal(k_noise, teacher.shape, teacher.dtype)

        def row(step, aux):
            info = step.info
            return (step.obs, env.scripted_actions(step.state, params), info["success"] & info["done"], info["done"])

        _, rows = rollout(env, params, pilot, obs, state, jax.random.split(key, bc.steps), record=row)
        return rows

    k_reset, k_run = jax.random.split(key)
    # jitted: run eagerly, a vmapped reset compiles one small program per primitive
    obs, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(k_reset, bc.num_envs), params)
    run = jax.jit(trainer.batch(one_env, in_axes=(0, 0, 0, None)))
    obs_rows, teacher, success, done = run(jax.random.split(k_run, bc.num_envs), states, obs, arrays)
    # (envs, steps, ...) -> (steps, envs, ...)
    swap = lambda x: jnp.swapaxes(x, 0, 1)      # noqa: E731
    return Demonstrations(obs=swap(obs_rows).astype(jnp.float32), actions=swap(teacher).astype(jnp.float32),
                          success=swap(success), done=swap(done))


def _r2(pred, target):
    """R² per action dimension ``(act,)`` of predictions ``(m, act)``."""
    sse = jnp.sum((pred - target) ** 2, axis=0)
    sst = jnp.sum((target - jnp.mean(target, axis=0)) ** 2, axis=0)
    return 1.0 - sse / jnp.maximum(sst, 1e-12)


def _held_out(bc, envs: int) -> int:
    """How many of ``envs`` environments are held out."""
    n_hold = max(1, int(round(bc.holdout * envs)))
    if n_hold >= envs:
        raise ValueError(f"algo.bc: {envs} environment(s) leave none to train on after holding out {n_hold}")
    return n_hold


def fit(trainer, ts, demos: Demonstrations, key):
    """``(state, stats)``: ``ts`` with the actor cloned from ``demos`` (module docstring);
    ``stats`` the fit's measures as arrays (:func:`report` makes them a dict)."""
    c = trainer.config
    bc = c.bc
    steps, envs = demos.obs.shape[:2]
    n_hold = _held_out(bc, envs)
    obs_size, act = demos.obs.shape[-1], demos.actions.shape[-1]
    train_obs = demos.obs[:, : envs - n_hold].reshape(-1, obs_size)
    train_act = demos.actions[:, : envs - n_hold].reshape(-1, act)
    hold_obs = demos.obs[:, envs - n_hold:].reshape(-1, obs_size)
    hold_act = demos.actions[:, envs - n_hold:].reshape(-1, act)
    obs_stats = RunningStats.create((obs_size,)).update(train_obs)

    def norm(x):
        return obs_stats.normalize(x) if c.normalize_obs else x

    n = train_obs.shape[0]
    mb = min(bc.minibatch_size, n)
    n_mb = n // mb
    tx = optax.adam(bc.lr)

    def loss(actor_params, x, y):
        mean, _ = trainer.actor.apply(actor_params, x)
        return jnp.mean(jnp.sum((mean - y) ** 2, axis=-1))

    @jax.jit
    def train(actor_params, key):
        opt_state = tx.init(actor_params)
        x_all, y_all = norm(train_obs), train_act

        def epoch(carry, k):
            p, o = carry
            perm = jax.random.permutation(k, n)[: n_mb * mb].reshape(n_mb, mb)

            def step(carry, idx):
                p, o = carry
                value, grads = jax.value_and_grad(loss)(p, x_all[idx], y_all[idx])
                updates, o = tx.update(grads, o, p)
                return (optax.apply_updates(p, updates), o), value

            (p, o), values = jax.lax.scan(step, (p, o), perm)
            return (p, o), jnp.mean(values)

        (p, _), history = jax.lax.scan(epoch, (actor_params, opt_state), jax.random.split(key, bc.epochs))
        return p, history

    actor_params, history = train(ts.params["actor"], key)
    log_std = jnp.full_like(actor_params["params"]["log_std"], np.log(bc.std))
    actor_params = {**actor_params, "params": {**actor_params["params"], "log_std": log_std}}

    @jax.jit
    def measure(p):
        pred_t, _ = trainer.actor.apply(p, norm(train_obs))
        pred_h, _ = trainer.actor.apply(p, norm(hold_obs))
        return (jnp.sqrt(jnp.mean((pred_t - train_act) ** 2)), jnp.sqrt(jnp.mean((pred_h - hold_act) ** 2)),
                _r2(pred_h, hold_act), jnp.std(hold_act, axis=0))

    rmse_train, rmse_hold, r2_hold, spread = measure(actor_params)
    params = {**ts.params, "actor": actor_params}
    arrays = {"actor": actor_params, "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}
    state = ts.replace(params=params, opt_state=trainer.tx.init(params), obs_stats=obs_stats, anchor=arrays)
    stats = {
        "episodes_ended": jnp.sum(demos.done),
        "teacher_success_rate": jnp.sum(demos.success) / jnp.maximum(jnp.sum(demos.done), 1),
        "final_train_loss": history[-1], "rmse_train": rmse_train, "rmse_holdout": rmse_hold,
        "r2_holdout": r2_hold, "label_std_holdout": spread,
    }
    return state, stats


def _joined(a: Demonstrations, b: Demonstrations) -> Demonstrations:
    """Both datasets, along the step axis: environment ``e`` of each is held out alike."""
    return jax.tree.map(lambda x, y: jnp.concatenate([x, y], axis=0), a, b)


def clone(trainer, ts, key):
    """``(state, stats)``: collect demonstrations and fit the actor to them; then, for each
    of ``bc.dagger_rounds``, let the clone fly, label the states it visits with the
    scripted team's actions, add them to the data and fit again (DAgger, Ross et al. 2011).
    ``stats``: the last fit's measures, and each round's episodes and the clone's success
    in them (``dagger_episodes``, ``dagger_success`` ``(rounds,)``)."""
    rounds = trainer.config.bc.dagger_rounds
    keys = jax.random.split(key, 2 * (rounds + 1))
    demos = collect(trainer, keys[0])
    state, stats = fit(trainer, ts, demos, keys[1])
    ended, success = [], []
    for r in range(rounds):
        more = collect(trainer, keys[2 + 2 * r], arrays=trainer.policy_arrays(state))
        ended.append(jnp.sum(more.done))
        success.append(jnp.sum(more.success) / jnp.maximum(jnp.sum(more.done), 1))
        demos = _joined(demos, more)
        state, stats = fit(trainer, ts, demos, keys[3 + 2 * r])
    stats["dagger_episodes"] = jnp.asarray(ended, jnp.int32).reshape(rounds)
    stats["dagger_success"] = jnp.asarray(success, jnp.float32).reshape(rounds)
    return state, stats


def report(trainer, stats: dict) -> dict:
    """:func:`clone`'s ``stats`` (of one run) as a JSON-ready dict: the data's sizes from
    the settings, the fit's measures, each DAgger round's episodes and the clone's success."""
    bc = trainer.config.bc
    n_agents = trainer.env.action_shape[0]
    n_hold = _held_out(bc, bc.num_envs)
    steps = bc.steps * (bc.dagger_rounds + 1)
    s = jax.device_get(stats)
    out = {
        "pairs": steps * bc.num_envs * n_agents, "train_pairs": steps * (bc.num_envs - n_hold) * n_agents,
        "holdout_environments": n_hold, "episodes_ended": int(s["episodes_ended"]),
        "teacher_success_rate": float(s["teacher_success_rate"]), "epochs": bc.epochs,
        "final_train_loss": float(s["final_train_loss"]), "rmse_train": float(s["rmse_train"]),
        "rmse_holdout": float(s["rmse_holdout"]), "r2_holdout": [float(v) for v in s["r2_holdout"]],
        "label_std_holdout": [float(v) for v in s["label_std_holdout"]],
        "team_steps": steps * bc.num_envs,
    }
    if bc.dagger_rounds:
        out["dagger"] = [{"episodes_ended": int(e), "clone_success_rate": float(r)}
                         for e, r in zip(s["dagger_episodes"], s["dagger_success"])]
    return out


def from_policy(trainer, ts, meta: dict, arrays: dict, where: str):
    """``ts`` starting from a saved policy (``algo.init: policy``; ``meta, arrays`` from
    :func:`mysim_jax.mappo.checkpoint.load_policy`), as :func:`fit` starts from the clone:
    its actor and observation normalisation, the exploration std ``bc.std``, the anchor on
    it, the optimiser reset; the critic and the state normalisation are ``ts``'s (fresh).
    A capture policy must have been trained on an environment whose observations and
    actions mean what this one's do (:func:`mysim_jax.mappo.policies.check_environment`);
    :class:`~mysim_jax.mappo.policies.PolicyError` naming ``where`` otherwise
    (:func:`~mysim_jax.mappo.policies.check_trained_on`, which a run calls before compiling)."""
    check_trained_on(meta, trainer.env, trainer.env_params, where)
    actor = jax.tree.map(jnp.asarray, arrays["actor"])
    mine = ts.params["actor"]
    if jax.tree.structure(actor) != jax.tree.structure(mine) or any(
            a.shape != b.shape for a, b in zip(jax.tree.leaves(actor), jax.tree.leaves(mine))):
        raise PolicyError(f"{where}: its actor's layers are not this trainer's (algo.hidden)")
    bc = trainer.config.bc
    actor = {**actor, "params": {**actor["params"], "log_std": jnp.full_like(actor["params"]["log_std"],
                                                                            np.log(bc.std))}}
    params = {**ts.params, "actor": actor}
    obs_stats = ts.obs_stats.replace(mean=jnp.asarray(arrays["obs_mean"], jnp.float32),
                                     var=jnp.asarray(arrays["obs_var"], jnp.float32),
                                     count=jnp.asarray(STARTED_COUNT, jnp.float32))
    anchor = {"actor": actor, "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}
    return ts.replace(params=params, opt_state=trainer.tx.init(params), obs_stats=obs_stats, anchor=anchor)


# the observation statistics of a saved policy count as this many samples when they go on
# being updated (bc.freeze_obs_norm false): a policy folder does not record how many it saw
STARTED_COUNT = 1.0e6
