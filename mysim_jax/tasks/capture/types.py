"""The capture environment's pytrees: its traced parameters (:class:`EnvParams`), one
environment's state (:class:`EnvState`) and what they hold (the per-episode draws
:class:`Episode` with their :class:`ObservationNoise`, and their :class:`Ranges`; the
estimation errors' levels :class:`PerceptionLevels` and the errors :class:`PerceptionErrors`).
Trained policies and checkpoints rely on their structure and field order."""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from mysim_jax.core.types import Params, State

# the fields of ObservationNoise and PerceptionLevels (the errors of PerceptionErrors) and the
# entries of a scene file's env.noise and env.perception they come from
CONFIG_NAMES = {"uav_pos": "uav_position", "uav_vel": "uav_velocity", "target_pos": "target_position",
                "target_vel": "target_velocity"}


@struct.dataclass
class ObservationNoise:
    """Standard deviations of the Gaussian noise on what each agent measures (``env.noise``,
    drawn per episode; every agent's noise is drawn independently, per axis). Each ``()``
    in the scene's dtype."""

    uav_pos: jnp.ndarray          # () m, on its own position (env.noise.uav_position)
    uav_vel: jnp.ndarray          # () m/s, on its own velocity (env.noise.uav_velocity)
    target_pos: jnp.ndarray       # () m, on the target's position (env.noise.target_position)
    target_vel: jnp.ndarray       # () m/s, on the target's velocity (env.noise.target_velocity)

    def stacked(self) -> jnp.ndarray:
        """The four as one ``(4,)`` array, in field order (the episode draws them as one)."""
        return jnp.stack([self.uav_pos, self.uav_vel, self.target_pos, self.target_vel])

    @classmethod
    def unstacked(cls, values) -> "ObservationNoise":
        """The inverse of :meth:`stacked`: ``values`` ``(4,)`` in field order."""
        return cls(uav_pos=values[0], uav_vel=values[1], target_pos=values[2], target_vel=values[3])


@struct.dataclass
class Episode:
    """What is drawn per episode (besides the target's spawn, which lives in the sim state)."""

    target_mass: jnp.ndarray      # () kg
    uav_mass_scale: jnp.ndarray   # () -
    wind_force: jnp.ndarray       # (3,) N on every UAV, world
    flee_acceleration: jnp.ndarray  # () m/s^2
    jink_acceleration: jnp.ndarray  # () m/s^2
    max_speed: jnp.ndarray        # () m/s
    noise: ObservationNoise       # the observation noise's standard deviations
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
class GaussMarkovLevel:
    """One first-order Gauss-Markov estimation error per policy step, independent per axis:
    ``e' = rho e + sigma √(1 - rho²) ξ``, started from its stationary distribution."""

    sigma: jnp.ndarray            # () stationary standard deviation, the quantity's unit (m or m/s)
    rho: jnp.ndarray              # () correlation over one policy step, exp(-policy_dt / correlation_time) (0: white)


@struct.dataclass
class PerceptionLevels:
    """The levels of the estimation errors the team flies on (``env.perception``; all zero
    when the team sees true states), named as the errors of :class:`PerceptionErrors`."""

    uav_pos: GaussMarkovLevel     # m, each UAV's own position estimate (env.perception.uav_position)
    uav_vel: GaussMarkovLevel     # m/s, its own velocity (env.perception.uav_velocity)
    target_pos: GaussMarkovLevel  # m, the team's fused target position (env.perception.target_position)
    target_vel: GaussMarkovLevel  # m/s, its velocity (env.perception.target_velocity)


@struct.dataclass
class EnvParams:
    """Traced environment parameters (vmap or change them without recompiling)."""

    sim: Params                   # the scene's nominal physics parameters
    start: State                  # the nominal first state (the target is placed by the reset)
    weights: jnp.ndarray          # (n_terms,) reward weights, REWARD_TERMS order, >= 0
    discount: jnp.ndarray         # () γ of the potential-based shaping
    ranges: Ranges
    perception: PerceptionLevels  # the estimation errors' levels (zeros: the team sees true states)
    target_delay: jnp.ndarray     # () the target estimate's latency over the policy period, in [0, 1]
    # (2,) per policy step: the probability of losing the target estimate while it is seen,
    # and of regaining it while lost (env.perception.target_dropout); zeros: never lost
    target_dropout: jnp.ndarray
    perception_scale: jnp.ndarray  # (2,) low, high of the per-episode factor on every error's sigma


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
    scale: jnp.ndarray               # () this episode's factor on every error's sigma (env.perception.scale)


@struct.dataclass
class EnvState:
    """State of one environment."""

    sim: State
    episode: Episode
    steps: jnp.ndarray            # () int32, policy steps taken this episode
    target_held: jnp.ndarray      # () bool, the target was held after the last step
    held_time: jnp.ndarray        # () s from the first held step of the current hold to the last
    touched: jnp.ndarray          # () bool, the target has touched the net this episode
    returns: jnp.ndarray          # (n_agents,) sum of rewards this episode
    potential: jnp.ndarray        # (n_shaping_terms, n_agents) weighted potential terms of this state
    perception: PerceptionErrors | None = None   # None unless the team flies on estimates
