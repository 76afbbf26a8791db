"""The ``env:`` block of a capture scene file: the scene as a multi-agent environment.

A scene with ``net:``, ``target:`` and quadrotors becomes an environment
(:mod:`mysim_jax.tasks.capture`) with this block. Everything has a default, so ``env: {}``
is a complete block::

    env:
      policy_rate: 25.0            # Hz: one action per 1/25 s (a whole number of sim.dt)
      rewards: {distance: 1.2, ..., success: 100, miss: 0, crash: 100}   # weights, >= 0 (the sign
                                   # is in the term); the paper's shaping and these outcomes by default
      discount: 0.99               # γ of the potential-based shaping (the learner's)
      reward_scales: {...}         # the length, speed and rate each shaped term saturates at
      success: {hold_time: 0.5, ...}
      failure: {max_tilt_deg: 80, ...}
      noise: {target_position: {low: 0, high: 0}, ...}   # observation noise sigma, drawn per episode
      perception: {uav_position: {sigma: 0.05, correlation_time: 3.0}, ...}   # fly on estimates
      randomize: {target_mass: {low: 0.08, high: 0.12}, wind_force: {low: [..], high: [..]}, ...}
      observe_top_thrust: false    # true: every UAV observes each UAV's top thrust (motor faults)
      fault_failsafe: none         # faulty_uav | team: no descent once a UAV has a motor fault

The episode's time limit is the scene's ``sim.t_end``. Every randomised quantity is a
``{low, high}`` range drawn uniformly per episode from the episode's key; ``low == high``
fixes it, ``low > high`` is an error. A draw replaces the scene's own value in the
environment (``env.randomize.target_mass`` replaces ``target.mass``, and so on:
:data:`REPLACED_BY_DRAWS`), so an override of such a value while its draw is on would be
ignored: :func:`drawn_value_problems` makes it an error that says how to fix the value.
Pydantic only: validating a file never imports JAX.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import yaml
from pydantic import Field, field_validator, model_validator

from mysim_jax.config.capture import BoxRange, Range
from mysim_jax.core.config_base import NonNegFloat, PosFloat, StrictModel

# The paper's eight terms and their weights (Table rewards): seven are the terms of the
# shaping potential, effort is a per-step cost (mysim_jax/tasks/rewards.py).
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
SHAPING_TERMS = ("distance", "alignment", "spin", "swing", "safe", "collision", "stability")
COST_TERMS = ("effort",)
# Outcomes beyond the paper (it has none), large enough by default that the paper's
# shaping cannot outweigh them over a default episode (return_bounds).
OUTCOME_WEIGHTS = {"success": 100.0, "miss": 0.0, "crash": 100.0}
OUTCOME_TERMS = tuple(OUTCOME_WEIGHTS)
REWARD_TERMS = tuple(PAPER_WEIGHTS) + OUTCOME_TERMS
# Potential terms that are bonuses (in [0, 1]); the others are penalties (in [-1, 0],
# ``safe`` in [-(n_agents - 1), 0]).
BONUS_TERMS = ("collision", "stability")

# The ways an episode can end without success, in the order they are reported. The
# target reaching the ground is a miss; every other failure is a crash.
FAILURES = ("uav_ground", "uav_tilt", "uav_altitude", "uav_uav_collision", "uav_target_collision",
            "target_ground", "non_finite")
MISSES = ("target_ground",)
CRASHES = tuple(f for f in FAILURES if f not in MISSES)


def return_bounds(weights: dict[str, float], n_agents: int, max_steps: int, discount: float) -> dict[str, float]:
    """Bounds on what shaping and costs can add to one agent's (undiscounted) episode
    return, for episodes of at most ``max_steps`` steps.

    With ``Φ`` in ``[−P, B]`` (``P`` the sum of the penalty weights, ``safe`` counted
    ``n_agents − 1`` times, ``B`` that of the bonuses), an episode's shaping is
    ``G = −Φ_0 + (γ − 1) Σ_{t=1}^{T−1} Φ_t + γ Φ_T`` (``Φ_T = 0`` when it ends by an
    outcome), so ``G`` lies in ``[−B − (T−1)(1−γ) B − γ P,  P + (T−1)(1−γ) P + γ B]``; the
    costs add ``[−w_effort T, 0]``. Returns ``shaping_low``, ``shaping_high``,
    ``cost_low`` and ``spread`` = (highest − lowest) shaping and cost together."""
    penalty = sum(weights[k] * (n_agents - 1 if k == "safe" else 1.0) for k in SHAPING_TERMS if k not in BONUS_TERMS)
    bonus = sum(weights[k] for k in BONUS_TERMS)
    tail = (max_steps - 1) * (1.0 - discount)
    low = -bonus - tail * bonus - discount * penalty
    high = penalty + tail * penalty + discount * bonus
    cost_low = -sum(weights[k] for k in COST_TERMS) * max_steps
    return {"shaping_low": low, "shaping_high": high, "cost_low": cost_low, "spread": high - low - cost_low}


def ranking_problems(weights: dict[str, float], n_agents: int, max_steps: int, discount: float) -> list[str]:
    """Why these weights could let an episode's shaping and costs outweigh its outcome
    (empty when they cannot: every caught episode then returns more than every missed one,
    and every missed one more than every crashed one)."""
    b = return_bounds(weights, n_agents, max_steps, discount)
    spread = b["spread"]
    problems = []
    if weights["success"] <= spread:
        problems.append(f"env.rewards.success = {weights['success']:g} must exceed {spread:.4g}, the largest spread of "
                        f"an episode's shaping and costs with these weights ({max_steps} policy steps, discount "
                        f"{discount:g}), or a missed episode could return more than a caught one: raise it or "
                        "lower the shaping weights")
    if weights["crash"] <= weights["miss"] + spread:
        problems.append(f"env.rewards.crash = {weights['crash']:g} must exceed rewards.miss + {spread:.4g} = "
                        f"{weights['miss'] + spread:.4g} (the largest spread of an episode's shaping and costs), or "
                        "a crashed episode could return more than a missed one: raise it or lower the shaping weights")
    return problems


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
    for ``hold_time`` without a break. An evading target whose scene has entanglement
    (``target.entanglement``) is held only while its entanglement is at least
    ``min_entanglement`` (1: its propulsion is lost); without entanglement it is unused."""

    hold_time: NonNegFloat = 0.5           # s
    max_relative_speed: PosFloat = 0.5     # m/s
    ground_clearance: NonNegFloat = 0.05   # m
    min_entanglement: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1.0


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


class DropoutConfig(StrictModel):
    """Losses of the target estimate (the cameras lose the target: occlusion, a missed
    detection, the target out of view): a two-state Markov chain per policy step, lost a
    ``fraction`` of the time on average, each loss lasting ``mean_duration`` on average
    (geometrically distributed in policy steps). While lost the team's target estimate
    coasts from the last one it had, as a track's prediction does: at the last velocity
    (a falling target: ballistically, under gravity). Each episode starts with the target
    seen."""

    fraction: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.0   # of the time lost
    mean_duration: PosFloat = 0.2                                              # s, of one loss


def dropout_per_step(dropout: DropoutConfig, policy_dt: float, where: str) -> tuple[float, float]:
    """``(p_lose, p_regain)`` per policy step of ``dropout`` at the policy period
    ``policy_dt`` (s): a loss ends with probability ``1 - exp(-policy_dt / mean_duration)``
    per step, and starts with the probability that keeps the lost fraction ``fraction``;
    ``ValueError`` naming ``where`` when no such probability exists."""
    p_regain = 1.0 - math.exp(-policy_dt / dropout.mean_duration)
    p_lose = p_regain * dropout.fraction / (1.0 - dropout.fraction)
    if p_lose > 1.0:
        raise ValueError(f"{where}: losses of mean_duration {dropout.mean_duration:g} s at a policy period of "
                         f"{policy_dt:g} s cannot fill a fraction {dropout.fraction:g} of the time (the target would "
                         "have to be lost again at every step); lengthen mean_duration or lower fraction")
    return p_lose, p_regain


class PerceptionConfig(StrictModel):
    """The team flies on estimates instead of true states: each UAV's own position and
    velocity as its visual-inertial odometry gives them (errors independent per UAV; the
    teammates' positions are their own estimates, shared), and the target's position and
    velocity as the team's fused localisation gives them (one estimate shared by every
    UAV). Both the observations and the scripted team (a residual policy's base) use them;
    attitudes, body rates and the net's centre stay true. ``noise`` is added on top.

    ``target_latency``: the target estimate's age (camera exposure, detection and fusion
    take time): the team sees the target's position and velocity of that long ago (linear
    between the true states of the last two policy steps, so at most one policy period),
    plus the estimation errors. The UAVs' own estimates have no latency.

    ``target_dropout``: the target estimate is lost at times and coasts meanwhile
    (:class:`DropoutConfig`).

    ``scale``: a factor on the four errors' ``sigma``, drawn uniformly per episode (the
    correlation times, latency and dropouts are kept): a team trained on a range of it
    expects estimates from better and worse trackers than the one its errors were fitted
    on. The default fixes it at 1."""

    uav_position: GaussMarkov = GaussMarkov()       # m
    uav_velocity: GaussMarkov = GaussMarkov()       # m/s
    target_position: GaussMarkov = GaussMarkov()    # m
    target_velocity: GaussMarkov = GaussMarkov()    # m/s
    target_latency: NonNegFloat = 0.0               # s, at most one policy period
    target_dropout: DropoutConfig | None = None     # None: the target estimate is never lost
    scale: Range = fixed(1.0)                       # -, per-episode factor on every sigma


class ThrustLossConfig(StrictModel):
    """A motor fault: one UAV, drawn per episode, keeps only ``fraction`` of its rotors'
    maximum thrust from ``time`` on (its rotors' top speed falls to √fraction of the
    nominal; 0: its rotors stop). The fault starts at the first policy step at or after
    ``time``; the other UAVs are not told."""

    fraction: Range                     # of the nominal maximum thrust, 0 to 1
    time: Range                         # s after the episode's start

    @field_validator("fraction")
    @classmethod
    def _at_most_one(cls, v):
        if v.high > 1.0:
            raise ValueError(f"a fraction of the nominal thrust is at most 1 (high = {v.high:g})")
        return v


class RandomizeConfig(StrictModel):
    """Per-episode draws beyond the target's spawn (which ``target.spawn`` ranges give).
    ``None`` keeps the scene's value; a range replaces it (:data:`REPLACED_BY_DRAWS`).
    ``uav_mass_scale`` multiplies every UAV's mass and inertia (the controller keeps
    assuming the nominal mass); ``wind_force`` is one force [N] on every UAV for the
    episode, added to the quadrotors' own ``wind.force`` (a force, not a wind speed); the
    evasive ranges apply to a maneuvering target; ``thrust_loss`` is a motor fault of one
    UAV (:class:`ThrustLossConfig`)."""

    target_mass: Range | None = None               # kg (inertia scales with it)
    uav_mass_scale: Range | None = None            # -
    wind_force: BoxRange | None = None             # N, world frame, on every UAV
    flee_acceleration: Range | None = None         # m/s^2
    jink_acceleration: Range | None = None         # m/s^2
    max_speed: Range | None = None                 # m/s
    thrust_loss: ThrustLossConfig | None = None    # one UAV's motor fault

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data):
        if isinstance(data, dict) and "wind" in data:
            raise ValueError("wind: renamed wind_force (a force in N on every UAV, not a wind speed): write "
                             "env.randomize.wind_force with the same {low, high}")
        return data

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
    # γ of the shaping F = γ Φ(s') − Φ(s): the learner's discount, so that the shaping leaves
    # the optimal policy unchanged (scripts/train.py's environments take algo.gamma instead:
    # make_env(config, discount=))
    discount: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.99
    reward_scales: RewardScales = RewardScales()
    success: SuccessConfig = SuccessConfig()
    failure: FailureConfig = FailureConfig()
    noise: NoiseConfig = NoiseConfig()
    perception: PerceptionConfig | None = None     # None: the team sees true states
    randomize: RandomizeConfig = RandomizeConfig()
    # Each UAV's observation ends with the UAVs' maximum thrusts as fractions of the nominal
    # (its own, then its teammates' in the teammates' order), and the critic's state with
    # all of them: 1 for a healthy UAV, the fault's fraction for a faulty one
    # (randomize.thrust_loss) from the policy step the fault starts. A flight controller
    # knows this from its motors (an ESC reports a failing motor; a motor that stays
    # saturated shows it); the team shares it as it shares positions.
    observe_top_thrust: bool = False
    # A motor-fault failsafe between the team's actions and the UAVs' setpoints (velocity
    # setpoints only): from the policy step a UAV's fault starts (randomize.thrust_loss),
    # the faulty UAV (``faulty_uav``) or every UAV (``team``) does not descend: its vertical
    # velocity setpoint is floored at 0. A UAV short of thrust sinks with the load of the
    # net and a caught target if it is let down; a flight controller knows its motors'
    # state, as with observe_top_thrust. It acts on whichever team flies (the scripted
    # team's setpoints too); ``none`` passes the actions as they are.
    fault_failsafe: Literal["none", "faulty_uav", "team"] = "none"

    @field_validator("rewards")
    @classmethod
    def _known(cls, v):
        unknown = sorted(set(v) - set(REWARD_TERMS))
        if unknown:
            raise ValueError(f"unknown reward term(s) {', '.join(repr(u) for u in unknown)}: the terms are "
                             f"{', '.join(REWARD_TERMS)}")
        return v

    @model_validator(mode="after")
    def _latency_within_a_period(self):
        if self.perception is not None and self.perception.target_latency > 1.0 / self.policy_rate:
            raise ValueError(f"perception.target_latency {self.perception.target_latency:g} s is more than one policy "
                             f"period (1 / policy_rate = {1.0 / self.policy_rate:g} s): the estimate is interpolated "
                             "between the last two policy steps; lower the latency or the policy rate")
        if self.perception is not None and self.perception.target_dropout is not None:
            dropout_per_step(self.perception.target_dropout, 1.0 / self.policy_rate, "perception.target_dropout")
        return self

    def weights(self) -> dict[str, float]:
        """Every term's weight: the file's, else the paper's (outcomes: OUTCOME_WEIGHTS)."""
        return {**PAPER_WEIGHTS, **OUTCOME_WEIGHTS, **self.rewards}


# Scene values that a per-episode draw replaces in the environment: (the value's dotted
# key, the draw of env.randomize that replaces it, unit).
REPLACED_BY_DRAWS = (
    ("target.mass", "target_mass", "kg"),
    ("target.propulsion.max_speed", "max_speed", "m/s"),
    ("target.propulsion.flee_acceleration", "flee_acceleration", "m/s^2"),
    ("target.propulsion.jink_acceleration", "jink_acceleration", "m/s^2"),
)


def _assigned(overrides) -> dict[str, Any]:
    """Every dotted key an override list assigns, with its value (a mapping value assigns
    each of its leaves: ``target={mass: 1}`` assigns ``target.mass``)."""
    out: dict[str, Any] = {}

    def walk(key: str, value):
        out[key] = value
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{key}.{k}", v)

    for ov in overrides:
        key, sep, text = ov.partition("=")
        if not sep:
            continue
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            continue                      # the scene loader reports it
        walk(".".join(p for p in key.strip().split(".") if p), value)
    return out


def drawn_value_problems(config, overrides, where: str = "--set") -> list[str]:
    """One line per override (``key=value``) that sets a scene value the environment
    replaces by a per-episode draw of ``config.env.randomize`` (the loaded scene, a
    SceneConfig with an ``env:`` block): the value would be ignored. Each line names the
    draw and how to fix the value for every episode (``low`` = ``high``), or how to turn
    the draw off. Empty when nothing is ignored (or the scene has no ``env:``)."""
    if getattr(config, "env", None) is None:
        return []
    assigned = _assigned(overrides)
    problems = []
    for key, draw, unit in REPLACED_BY_DRAWS:
        if key not in assigned:
            continue
        r = getattr(config.env.randomize, draw)
        if r is None:
            continue
        value = assigned[key]
        problems.append(
            f"{where} {key}={value}: env.randomize.{draw} draws it per episode ({r.low:g} to {r.high:g} {unit}) and "
            f"replaces {key} in the environment, so the value would be ignored; to fly with {value} {unit} in every "
            f"episode set env.randomize.{draw}={{low: {value}, high: {value}}} instead (or "
            f"env.randomize.{draw}=null to use {key})")
    return problems
