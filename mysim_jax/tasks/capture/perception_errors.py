"""Flying on estimates (``env.perception``): the estimation errors of the UAVs' and the
target's positions and velocities as first-order Gauss-Markov processes, the target
estimate's latency and dropouts, and what the team knows from them
(:meth:`PerceptionErrorsMixin.estimates`); with the error levels per policy step that a
scene file's ``env.perception`` gives (:func:`perception_levels`, :func:`target_delay`,
:func:`target_dropout`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.config.env import dropout_per_step
from mysim_jax.core import rng
from mysim_jax.core.config_base import ConfigError
from mysim_jax.core.types import State
from mysim_jax.tasks.capture.types import (CONFIG_NAMES, EnvParams, EnvState, GaussMarkovLevel, PerceptionErrors,
                                           PerceptionLevels)


class PerceptionErrorsMixin:
    """The estimation errors of :class:`~mysim_jax.tasks.capture.env.CaptureEnv` (whose
    fields these methods read)."""

    def _error_shapes(self):
        n = self.n_agents
        return {"uav_pos": (n, 3), "uav_vel": (n, 3), "target_pos": (3,), "target_vel": (3,)}

    def _target_now(self, sim: State):
        phys = sim.phys
        return {"target_pos_before": phys.body_pos[self.target_body],
                "target_vel_before": phys.body_vel[self.target_body]}

    def _draw_errors(self, key, params: EnvParams, dtype, sim: State) -> PerceptionErrors:
        """The episode's factor on every sigma, drawn uniformly from
        ``params.perception_scale``, and the errors drawn from their stationary
        distributions at that factor (an episode's first state ``sim``)."""
        keys = jax.random.split(key, 4)
        shapes = self._error_shapes()
        low, high = params.perception_scale[0].astype(dtype), params.perception_scale[1].astype(dtype)
        # its own stream: a fixed factor (the default 1) leaves every error as without it
        scale = low + (high - low) * jax.random.uniform(jax.random.fold_in(key, 9), (), dtype)
        xi = rng.normal_each(keys, list(shapes.values()), dtype)
        e = {name: scale * getattr(params.perception, name).sigma.astype(dtype) * xi[i]
             for i, name in enumerate(shapes)}
        now = self._target_now(sim)
        return PerceptionErrors(**e, **now, target_lost=jnp.zeros((), bool),
                                target_last_pos=now["target_pos_before"] + e["target_pos"],
                                target_last_vel=now["target_vel_before"] + e["target_vel"],
                                target_lost_steps=jnp.zeros((), jnp.int32), scale=scale)

    def _step_errors(self, key, errors: PerceptionErrors, params: EnvParams, dtype, before: State,
                     after: State) -> PerceptionErrors:
        """One policy period of every Gauss-Markov error: ``e' = rho e + sigma √(1 - rho²) ξ``;
        ``before``: the state the period started from (the target's, for the latency);
        ``after``: the state it ended in; every ``sigma`` at the episode's factor
        ``errors.scale``. Then one step of the target estimate's losses: lost
        (seen) it is regained (lost) with probability ``params.target_dropout[1]`` (``[0]``);
        while seen, the estimate is remembered, while lost it ages."""
        keys = jax.random.split(key, 4)
        shapes = self._error_shapes()
        xi = rng.normal_each(keys, list(shapes.values()), dtype)
        new = {}
        for i, name in enumerate(shapes):
            level = getattr(params.perception, name)
            sigma, rho = errors.scale * level.sigma.astype(dtype), level.rho.astype(dtype)
            drive = sigma * jnp.sqrt(jnp.maximum(1.0 - rho * rho, 0.0))
            new[name] = (rho * getattr(errors, name) + drive * xi[i]).astype(dtype)
        u = jax.random.uniform(jax.random.fold_in(key, 7), (), dtype)
        p_lose, p_regain = params.target_dropout[0].astype(dtype), params.target_dropout[1].astype(dtype)
        lost = jnp.where(errors.target_lost, u >= p_regain, u < p_lose)
        fresh = PerceptionErrors(**new, **self._target_now(before), target_lost=lost,
                                 target_last_pos=errors.target_last_pos, target_last_vel=errors.target_last_vel,
                                 target_lost_steps=errors.target_lost_steps, scale=errors.scale)
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


def perception_levels(config, policy_dt: float, dtype) -> PerceptionLevels:
    """The levels of ``env.perception``'s four errors per policy step (``config``; zeros
    when it is None), in ``dtype``."""
    def level(gm):
        sigma, tau = (0.0, 0.0) if gm is None else (float(gm.sigma), gm.correlation_time)
        rho = float(np.exp(-policy_dt / tau)) if tau > 0 else 0.0
        return GaussMarkovLevel(sigma=jnp.asarray(sigma, dtype), rho=jnp.asarray(rho, dtype))

    return PerceptionLevels(**{name: level(None if config is None else getattr(config, field))
                               for name, field in CONFIG_NAMES.items()})


def perception_scale(config) -> tuple[float, float]:
    """``(low, high)`` of ``env.perception.scale`` ((1, 1) without perception)."""
    return (1.0, 1.0) if config is None else (config.scale.low, config.scale.high)


def target_delay(config, policy_dt: float) -> float:
    """``env.perception.target_latency`` over the policy period (0 without perception)."""
    if config is None or config.target_latency == 0.0:
        return 0.0
    if config.target_latency > policy_dt * (1 + 1e-9):
        raise ConfigError(f"env.perception.target_latency {config.target_latency:g} s is more than the policy period "
                          f"{policy_dt:g} s (control steps x sim.dt): lower it or the policy rate")
    return min(config.target_latency / policy_dt, 1.0)


def target_dropout(config, policy_dt: float) -> tuple[float, float]:
    """``(p_lose, p_regain)`` per policy step of ``env.perception.target_dropout`` ((0, 0):
    never lost)."""
    if config is None or config.target_dropout is None:
        return 0.0, 0.0
    try:
        return dropout_per_step(config.target_dropout, policy_dt, "env.perception.target_dropout")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
