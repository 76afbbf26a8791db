"""What the capture environment draws per episode: the ranges of a scene file
(:func:`episode_ranges`), the draws of one episode (:meth:`RandomisationMixin.draw_episode`),
the physics parameters they give (:meth:`RandomisationMixin.episode_params`, with the motor
fault of ``env.randomize.thrust_loss``: :meth:`RandomisationMixin.faulted`), and a training
curriculum's scaling of the evading target's ranges (:func:`scaled_target_ranges`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import rng
from mysim_jax.core.types import Params
from mysim_jax.effects.target import TARGET
from mysim_jax.effects.wind import WIND
from mysim_jax.tasks.capture.types import CONFIG_NAMES, Episode, EnvParams, ObservationNoise, Ranges


class RandomisationMixin:
    """The per-episode draws of :class:`~mysim_jax.tasks.capture.env.CaptureEnv` (whose
    fields these methods read)."""

    def draw_episode(self, key, ranges: Ranges) -> Episode:
        """One episode's draws, uniform in ``ranges``: one draw per field (the scene's
        dtype), each from its own key, in field order; the observation noise's four
        standard deviations are one ``(4,)`` draw."""
        low, high = (r.replace(noise=r.noise.stacked()) for r in (ranges.low, ranges.high))
        leaves_low, treedef = jax.tree.flatten(low)
        leaves_high = jax.tree.leaves(high)
        keys = jax.random.split(key, len(leaves_low))
        drawn = rng.uniform_each(keys, [lo.shape for lo in leaves_low], leaves_low[0].dtype, leaves_low, leaves_high)
        episode = jax.tree.unflatten(treedef, drawn)
        return episode.replace(noise=ObservationNoise.unstacked(episode.noise))

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
        tp = TARGET.params(sim).replace(flee_acceleration=ep.flee_acceleration,
                                        jink_acceleration=ep.jink_acceleration, max_speed=ep.max_speed)
        sim = TARGET.with_params(sim.replace(body_mass=body_mass, body_inertia=inertia), tp)
        if self.randomized_wind:
            wind = WIND.params(sim)
            sim = WIND.with_params(sim, wind.replace(force=wind.force + ep.wind_force[None, :]))
        return sim

    def faulted(self, sim_params: Params, ep: Episode, steps) -> Params:
        """``sim_params`` with the episode's motor fault (``env.randomize.thrust_loss``) in
        force for the policy step that starts after ``steps`` steps: from the first step
        at or after the fault's time, the faulty UAV's rotor top speed is √fraction of the
        nominal (its maximum thrust ``fraction`` of the nominal)."""
        qp = sim_params.quadrotor
        scale = jnp.sqrt(self.top_thrust_fractions(ep, steps, qp.omega_max.dtype))
        return sim_params.replace(quadrotor=qp.replace(omega_max=qp.omega_max * scale))

    def top_thrust_fractions(self, ep: Episode, steps, dtype):
        """``(n_agents,)``: each UAV's maximum thrust, as a fraction of its nominal one, for
        the policy step that starts after ``steps`` steps: the faulty UAV's fraction from
        the fault on (:meth:`faulted`), 1 otherwise (every UAV without
        ``env.randomize.thrust_loss``)."""
        if not self.thrust_loss:
            return jnp.ones((self.n_agents,), dtype)
        started = steps.astype(dtype) * self.policy_dt >= ep.thrust_loss_time
        faulty = jnp.arange(self.n_agents) == jnp.minimum(jnp.floor(ep.thrust_loss_uav), self.n_agents - 1)
        return jnp.where(started & faulty, ep.thrust_fraction, 1.0).astype(dtype)


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


def episode_ranges(config, dtype, n_agents: int) -> Ranges:
    """The per-episode ranges of a capture SceneConfig (``env.randomize``, ``env.noise``;
    a value not drawn is fixed at the scene's own), in ``dtype``."""
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
        "noise": tuple(ObservationNoise(**{name: jnp.asarray(getattr(getattr(env.noise, field), side), dtype)
                                           for name, field in CONFIG_NAMES.items()})
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
