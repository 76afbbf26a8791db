"""The ``env:`` block of a capture scene file: the scene as a multi-agent environment.

A scene with ``net:``, ``target:`` and quadrotors becomes an environment
(:mod:`mysim_jax.tasks.capture`) with this block. Everything has a default, so ``env: {}``
is a complete block::

    env:
      policy_rate: 25.0            # Hz: one action per 1/25 s (a whole number of sim.dt)
      rewards: {distance: 1.2, ...}   # weights, >= 0 (the sign is in the term); the paper's by default
      reward_scales: {...}         # the length, speed and rate each shaped term saturates at
      success: {hold_time: 0.5, ...}
      failure: {max_tilt_deg: 80, ...}
      noise: {target_position: {low: 0, high: 0}, ...}   # observation noise sigma, drawn per episode
      perception: {uav_position: {sigma: 0.05, correlation_time: 3.0}, ...}   # fly on estimates
      randomize: {target_mass: {low: 0.08, high: 0.12}, wind: {low: [..], high: [..]}, ...}

The episode's time limit is the scene's ``sim.t_end``. Every randomised quantity is a
``{low, high}`` range drawn uniformly per episode from the episode's key; ``low == high``
fixes it, ``low > high`` is an error. Pydantic only: validating a file never imports JAX.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator, model_validator

from mysim_jax.config_base import NonNegFloat, PosFloat, StrictModel
from mysim_jax.tasks.config import BoxRange

# The paper's eight terms and their weights (Table rewards).
PAPER_WEIGHTS = {
    "distance": 1.2,
    "alignment": 0.6,
    "spin": 0.8,
    "effort": 0.1,
    "swing": 0.8,
    "safe": 0.5,
    "collision": 2.8,
    "stability": 4.5,
}
# Terminal terms beyond the paper (off by default, so the default reward is the paper's).
EXTRA_WEIGHTS = {"success": 0.0, "failure": 0.0}
REWARD_TERMS = tuple(PAPER_WEIGHTS) + tuple(EXTRA_WEIGHTS)

# The ways an episode can end without success, in the order they are reported.
FAILURES = ("uav_ground", "uav_tilt", "uav_altitude", "uav_uav_collision", "uav_target_collision",
            "target_ground", "non_finite")


class Range(StrictModel):
    """A scalar range ``low <= v <= high``, drawn uniformly (``low == high`` fixes it)."""

    low: NonNegFloat
    high: NonNegFloat

    @model_validator(mode="after")
    def _ordered(self):
        if self.low > self.high:
            raise ValueError(f"empty range: low ({self.low:g}) > high ({self.high:g})")
        return self


def fixed(value: float) -> Range:
    return Range(low=value, high=value)


class RewardScales(StrictModel):
    """Where each shaped term saturates (``tanh(x / scale)``; mysim_jax/tasks/rewards.py)."""

    distance: PosFloat = 1.0          # m, UAV's slot to the target, horizontally
    alignment: PosFloat = 1.0         # m/s, UAV to target horizontal velocity
    spin: PosFloat = 1.0              # rad/s, body rate
    swing: PosFloat = 0.5             # m, net centre off the formation centre, horizontally
    safe_distance: PosFloat = 0.8     # m, UAV-UAV distance below which "safe" penalises
    stability: PosFloat = 0.5         # m/s, target speed relative to the net
    contact_margin: NonNegFloat = 0.01   # m, target-to-line gap still counted as touching


class SuccessConfig(StrictModel):
    """The target is **held** when it is inside the net's outline (horizontally, in the
    polygon of the border knots), below every tether attachment, slower than
    ``max_relative_speed`` relative to the net's mean knot velocity, and its lowest point
    is ``ground_clearance`` above the ground; the episode succeeds once it has been held
    for ``hold_time`` without a break."""

    hold_time: NonNegFloat = 0.5           # s
    max_relative_speed: PosFloat = 0.5     # m/s
    ground_clearance: NonNegFloat = 0.05   # m


class FailureConfig(StrictModel):
    """Thresholds of the failures (checked after every policy step)."""

    uav_radius: PosFloat = 0.15            # m, a UAV's collision sphere
    ground_clearance: NonNegFloat = 0.05   # m: a UAV or the target this close to the ground crashed
    max_tilt_deg: Annotated[float, Field(gt=0, le=180)] = 80.0   # deg, body z from world z
    min_altitude: NonNegFloat = 1.0        # m, lowest UAV centre (the net drags below ~1.5 m)
    max_altitude: PosFloat = 15.0          # m, highest UAV centre


class NoiseConfig(StrictModel):
    """Observation noise: Gaussian, standard deviation drawn per episode from each range.
    Each agent measures its own position and velocity and the target's, independently."""

    uav_position: Range = fixed(0.0)       # m
    uav_velocity: Range = fixed(0.0)       # m/s
    target_position: Range = fixed(0.0)    # m
    target_velocity: Range = fixed(0.0)    # m/s


class GaussMarkov(StrictModel):
    """A first-order Gauss-Markov (Ornstein-Uhlenbeck) error, independent per axis:
    stationary standard deviation ``sigma`` and correlation time ``correlation_time`` (0:
    white, a new draw every policy step). It starts each episode from its stationary
    distribution; :func:`mysim_jax.perception.metrics.gauss_markov_fit` fits both numbers
    to a measured estimation error."""

    sigma: NonNegFloat = 0.0               # the quantity's unit (m or m/s)
    correlation_time: NonNegFloat = 0.0    # s


class PerceptionConfig(StrictModel):
    """The team flies on estimates instead of true states: each UAV's own position and
    velocity as its visual-inertial odometry gives them (errors independent per UAV; the
    teammates' positions are their own estimates, shared), and the target's position and
    velocity as the team's fused localisation gives them (one estimate shared by every
    UAV). Both the observations and the scripted team (a residual policy's base) use them;
    attitudes, body rates and the net's centre stay true. ``noise`` is added on top."""

    uav_position: GaussMarkov = GaussMarkov()       # m
    uav_velocity: GaussMarkov = GaussMarkov()       # m/s
    target_position: GaussMarkov = GaussMarkov()    # m
    target_velocity: GaussMarkov = GaussMarkov()    # m/s


class RandomizeConfig(StrictModel):
    """Per-episode draws beyond the target's spawn (which ``target.spawn`` ranges give).
    ``None`` keeps the scene's value. ``uav_mass_scale`` multiplies every UAV's mass and
    inertia (the controller keeps assuming the nominal mass); ``wind`` is one force [N] on
    every UAV for the episode; the evasive ranges apply to a maneuvering target."""

    target_mass: Range | None = None               # kg (inertia scales with it)
    uav_mass_scale: Range | None = None            # -
    wind: BoxRange | None = None                   # N, world frame
    flee_acceleration: Range | None = None         # m/s^2
    jink_acceleration: Range | None = None         # m/s^2
    max_speed: Range | None = None                 # m/s

    @field_validator("target_mass", "uav_mass_scale")
    @classmethod
    def _positive(cls, v):
        if v is not None and v.low <= 0.0:
            raise ValueError(f"must be positive (low = {v.low:g})")
        return v


class EnvConfig(StrictModel):
    """The environment block (module docstring)."""

    policy_rate: PosFloat = 25.0           # Hz
    rewards: dict[str, NonNegFloat] = {}   # term -> weight; missing terms keep their default
    reward_scales: RewardScales = RewardScales()
    success: SuccessConfig = SuccessConfig()
    failure: FailureConfig = FailureConfig()
    noise: NoiseConfig = NoiseConfig()
    perception: PerceptionConfig | None = None     # None: the team sees true states
    randomize: RandomizeConfig = RandomizeConfig()

    @field_validator("rewards")
    @classmethod
    def _known(cls, v):
        unknown = sorted(set(v) - set(REWARD_TERMS))
        if unknown:
            raise ValueError(f"unknown reward term(s) {', '.join(repr(u) for u in unknown)}: the terms are "
                             f"{', '.join(REWARD_TERMS)}")
        return v

    def weights(self) -> dict[str, float]:
        """Every term's weight: the file's, else the paper's (extras: 0)."""
        return {**PAPER_WEIGHTS, **EXTRA_WEIGHTS, **self.rewards}
