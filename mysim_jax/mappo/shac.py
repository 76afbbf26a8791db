"""SHAC: short-horizon actor-critic through the differentiable simulator (Xu et al., ICLR 2022).

    trainer = make_trainer(config.algo, env, env_params)   # a ShacTrainer when algo.name is shac
    state, metrics = trainer.iteration(state)              # as for PPO

The same networks, observation and action spaces, warm starts, model selection and run
files as MAPPO (:class:`~mysim_jax.mappo.trainer.Trainer`, which :class:`ShacTrainer`
extends); only the update differs.

**Actor** (one gradient step per iteration). The ``num_envs`` environments fly
``num_steps`` policy steps with reparameterised actions ``a = mu(o) + sigma * xi``, cut
into windows of ``h`` steps (``shac.horizon``; by default one window of ``num_steps``).
The actor's loss is minus the mean over environments, agents and steps of each window's
discounted reward, bootstrapped by the critic at the window's end:

    L = -1 / (T B A) * sum_{windows} sum_{b, i} [ sum_t gamma^(t - t0) r_t + gamma^(t1 - t0) V(s_t1) ]

differentiated through every policy step of the simulator inside a window (``jax.grad``
through the environment; each step rematerialised in the backward pass,
``jax.checkpoint``, so memory holds one step's intermediates at a time) and not across
windows (the state's gradient is stopped at a window's start, as truncated
backpropagation through time does). An episode that ends inside a window adds its
discounted rewards up to its end (and, cut by the time limit, the critic's value of its
last state); the fresh episode that follows starts its own sum (``t0``). The outcome
rewards are steps (no gradient); what the gradient sees is the shaping, the costs and the
critic's value (``shac.value_gradient: false`` keeps the value in the loss without its
gradient through the state: the actor then follows the window's rewards alone). The
gradient is clipped to ``max_grad_norm`` (global norm) and applied with Adam at ``lr``
(``lr_schedule`` over the iterations); a gradient that is not finite is skipped
(``updates_applied`` 0). With a warm start the anchor pulls the actor's means towards the
start's, and the critic's warm-up holds the actor, as for PPO.

**Critic** (as PPO's): TD(lambda) targets of the same rollout (GAE with ``gamma`` and
``gae_lambda``, the values of the critic before the update), ``update_epochs`` passes over
``num_minibatches`` shuffled minibatches with Adam at ``shac.critic_lr``, values clipped
around the old ones (``value_clip_eps``) and normalised (``value_norm``).

Where the gradient is usable sets the window: over more than a few policy steps the
backward pass through the net grows exponentially (docs/gradients.md), so ``h`` is short
and the critic carries the rest of the episode; a rollout of several windows gives the
critic's targets more steps than one window would.
"""

from __future__ import annotations

from functools import cached_property

import jax
import jax.numpy as jnp
import optax

from mysim_jax.mappo.losses import gaussian_entropy, gaussian_log_prob, value_loss
from mysim_jax.mappo.trainer import Trainer, TrainerState, Transition


class ShacTrainer(Trainer):
    """SHAC on ``env`` (module docstring): :class:`~mysim_jax.mappo.trainer.Trainer` with
    the actor's update through the simulator. ``config`` an
    :class:`~mysim_jax.mappo.config.AlgoConfig` with ``name: shac``."""

    def __post_init__(self):
        super().__post_init__()
        if self.mesh is not None:
            raise ValueError("algo.name: shac runs on one device (run.devices)")

    @property
    def horizon(self) -> int:
        """Policy steps the actor's gradient crosses (``shac.horizon``, else ``num_steps``)."""
        c = self.config
        return c.num_steps if c.shac.horizon is None else c.shac.horizon

    def memory_needs(self) -> dict:
        """PPO's parts (:meth:`Trainer.memory_needs`) and what the actor's backward pass
        keeps: the residuals reverse mode saves over the rollout (every step's carried
        environment state, the networks' activations), counted from ``jax.eval_shape`` of
        the loss's ``jax.vjp`` (traced, not compiled)."""
        needs = super().memory_needs()
        ts = jax.eval_shape(self.init, jax.random.PRNGKey(0))
        saved = jax.eval_shape(lambda t: jax.vjp(lambda a: self._actor_loss(a, t, 1.0, 0.0)[0],
                                                 t.params["actor"])[1], ts)
        needs["backward pass"] = (sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(saved)),
                                  "algo.num_envs x algo.num_steps")
        return needs

    # --- optimisers: one per network --------------------------------------------------
    def _schedule(self):
        """The actor's learning rate as a function of its steps taken (one per iteration)."""
        c = self.config
        if c.lr_schedule == "linear":
            return optax.linear_schedule(c.lr, 0.0, c.num_iterations)
        return optax.constant_schedule(c.lr)

    def learning_rate(self, iteration) -> float:
        """The actor's learning rate at iteration ``iteration`` (0-based)."""
        return float(self._schedule()(iteration))

    @cached_property
    def actor_tx(self) -> optax.GradientTransformation:
        return optax.chain(optax.clip_by_global_norm(self.config.max_grad_norm), optax.adam(self._schedule()))

    @cached_property
    def critic_tx(self) -> optax.GradientTransformation:
        c = self.config
        lr = c.lr if c.shac.critic_lr is None else c.shac.critic_lr
        return optax.chain(optax.clip_by_global_norm(c.max_grad_norm), optax.adam(lr, eps=1e-5))

    def _optimizer(self):
        """Initialises ``{"actor": ..., "critic": ...}`` optimiser states (:attr:`actor_tx`,
        :attr:`critic_tx`); the iteration updates each with its own."""
        def init(params):
            return {"actor": self.actor_tx.init(params["actor"]), "critic": self.critic_tx.init(params["critic"])}

        def update(*_):
            raise TypeError("ShacTrainer updates its networks with actor_tx and critic_tx")

        return optax.GradientTransformation(init, update)

    # --- the actor's loss through the simulator ----------------------------------------
    def _actor_loss(self, actor_params, ts: TrainerState, policy_coef, anchor_coef):
        """``(loss, (rollout, end, actor loss, anchor loss))``: the actor's loss (module
        docstring) with the anchor, the rollout's
        :class:`~mysim_jax.mappo.trainer.Transition` (gradients stopped) and the
        environments, observations, global states and key after it."""
        c = self.config
        h = self.horizon
        params = {**ts.params, "actor": actor_params}
        step_batch = jax.checkpoint(self._env_step(ts.ranges))
        gamma = c.gamma
        sg = jax.lax.stop_gradient

        def values(gs):
            """The critic's values of global states, with their gradient through the
            state unless ``shac.value_gradient`` is off."""
            return self._values(params, ts.ret_stats, ts.state_stats, gs if c.shac.value_gradient else sg(gs))

        def close(carry):
            """Ends the gradient window: the running episodes' sums bootstrapped by the
            critic at the window's end, added to the total; the state's gradient cut."""
            env_state, obs, gstate, key, acc, disc, live, total = carry
            total = total + jnp.where(live, acc + disc * values(gstate), 0.0)
            zeros = jnp.zeros_like(acc)
            return (sg(env_state), sg(obs), sg(gstate), key, zeros, jnp.ones_like(disc), jnp.zeros_like(live), total)

        def one(carry, t):
            carry = jax.lax.cond((t > 0) & (t % h == 0), close, lambda x: x, carry)
            env_state, obs, gstate, key, acc, disc, live, total = carry
            key, k_act, k_step = jax.random.split(key, 3)
            obs_n = self._norm_obs(ts.obs_stats, obs)
            mean, log_std = self.actor.apply(actor_params, obs_n)
            action = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape, mean.dtype)
            obs2, env_state2, reward, _, truncated, info = step_batch(jax.random.split(k_step, c.num_envs),
                                                                      env_state, action)
            reward = reward.astype(jnp.float32)
            done = info["done"][:, None]
            acc = acc + disc * reward
            boot = reward
            if c.bootstrap_time_limit:
                cut = truncated[:, None].astype(jnp.float32)
                final_value = values(info["final_global_state"].astype(jnp.float32))
                acc = acc + disc * gamma * final_value * cut
                boot = reward + gamma * sg(final_value) * cut
            total = total + jnp.where(done, acc, 0.0)
            acc, disc = jnp.where(done, 0.0, acc), jnp.where(done, 1.0, disc * gamma)
            live = jnp.broadcast_to(~done, live.shape)
            tr = Transition(obs=sg(obs_n), critic_in=self.critic_input(self._norm_obs(ts.state_stats, sg(gstate))),
                            action=sg(action), log_prob=sg(gaussian_log_prob(action, mean, log_std)),
                            value=sg(values(gstate)), reward=sg(boot), done=info["done"], raw_obs=sg(obs),
                            raw_state=sg(gstate), success=info["success"] & info["done"],
                            episode_return=jnp.mean(info["episode_return"], axis=-1).astype(jnp.float32),
                            episode_length=info["episode_length"], step_reward=sg(jnp.mean(reward, axis=-1)))
            gstate2 = info["global_state"].astype(jnp.float32)
            return (env_state2, obs2.astype(jnp.float32), gstate2, key, acc, disc, live, total), tr

        zeros = jnp.zeros((c.num_envs, self.n_agents), jnp.float32)
        carry = (ts.env_state, ts.obs, ts.global_state, ts.key, zeros, jnp.ones_like(zeros),
                 jnp.zeros(zeros.shape, bool), zeros)
        carry, traj = jax.lax.scan(one, carry, jnp.arange(c.num_steps))
        env_state, obs, gstate, key, _, _, _, total = close(carry)
        loss = -jnp.mean(total) / c.num_steps
        if self.uses_anchor:
            mean, _ = self.actor.apply(actor_params, traj.obs)
            anchor = jnp.mean(jnp.sum((mean - self.anchor_means(ts.anchor, traj.raw_obs)) ** 2, axis=-1))
        else:
            anchor = jnp.float32(0.0)
        end = sg((env_state, obs, gstate, key))
        return policy_coef * (loss + anchor_coef * anchor), (traj, end, loss, anchor)

    # --- one iteration -----------------------------------------------------------------
    def _critic_update(self, ts: TrainerState, traj: Transition, targets, ret_stats, key):
        """The critic after ``update_epochs`` passes of minibatch Adam on the value loss
        (module docstring): ``(critic params, critic optimiser state, value losses)``."""
        c = self.config

        def units(x):
            return (x - ret_stats.mean) / ret_stats.std if c.value_norm else x

        n = c.batch_size
        data = {"critic_in": traj.critic_in, "target": units(targets), "old_value": units(traj.value)}
        data = jax.tree.map(lambda x: x.reshape((n,) + x.shape[2:]), data)

        def loss(p, mb):
            return value_loss(self.critic.apply(p, mb["critic_in"]), mb["old_value"], mb["target"], c.value_clip_eps)

        def minibatch(carry, mb):
            p, opt = carry
            vl, g = jax.value_and_grad(loss)(p, mb)
            updates, opt = self.critic_tx.update(g, opt, p)
            return (optax.apply_updates(p, updates), opt), vl

        def epoch(carry, k):
            perm = jax.random.permutation(k, n)
            shuffled = jax.tree.map(lambda x: x[perm].reshape((c.num_minibatches, c.minibatch_size) + x.shape[1:]),
                                    data)
            return jax.lax.scan(minibatch, carry, shuffled)

        (p, opt), losses = jax.lax.scan(epoch, (ts.params["critic"], ts.opt_state["critic"]),
                                        jax.random.split(key, c.update_epochs))
        return p, opt, losses

    def _iteration(self, ts: TrainerState, knobs: dict | None = None):
        knobs = self.knobs() if knobs is None else knobs
        policy_coef, anchor_coef = self.schedule(ts.iteration, knobs)
        (_, (traj, end, actor_loss, anchor)), grads = jax.value_and_grad(self._actor_loss, has_aux=True)(
            ts.params["actor"], ts, policy_coef, anchor_coef)
        env_state, obs, gstate, key = end
        grad_norm = optax.tree.norm(grads)
        finite = jnp.isfinite(grad_norm)
        grads = jax.tree.map(lambda g: jnp.where(finite, g, 0.0), grads)
        updates, new_opt = self.actor_tx.update(grads, ts.opt_state["actor"], ts.params["actor"])
        actor, actor_opt = jax.tree.map(lambda old, new: jnp.where(finite, new, old),
                                        (ts.params["actor"], ts.opt_state["actor"]),
                                        (optax.apply_updates(ts.params["actor"], updates), new_opt))

        _, targets, ret_stats = self._targets(ts, traj, gstate)
        key, k_critic = jax.random.split(key)
        critic, critic_opt, value_losses = self._critic_update(ts, traj, targets, ret_stats, k_critic)
        log_std = ts.params["actor"]["params"]["log_std"]
        metrics = {"policy_loss": actor_loss, "value_loss": jnp.mean(value_losses),
                   "entropy": jnp.mean(gaussian_entropy(log_std)), "grad_norm": grad_norm,
                   "updates_applied": finite.astype(jnp.float32), "policy_coef": policy_coef,
                   "anchor_coef": anchor_coef}
        if self.uses_anchor:
            metrics["anchor_loss"] = anchor
        return self._finish(ts, traj, targets, metrics, params={"actor": actor, "critic": critic},
                            opt_state={"actor": actor_opt, "critic": critic_opt}, ret_stats=ret_stats,
                            env_state=env_state, obs=obs, global_state=gstate, key=key)


def make_trainer(config, env, env_params, **kwargs) -> Trainer:
    """The trainer of ``config.name``: :class:`~mysim_jax.mappo.trainer.Trainer` (``ppo``) or
    :class:`ShacTrainer` (``shac``); ``kwargs`` as theirs (``mesh``, ``curriculum``)."""
    cls = ShacTrainer if config.name == "shac" else Trainer
    return cls(config, env, env_params, **kwargs)
