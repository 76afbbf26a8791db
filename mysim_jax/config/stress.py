"""The stress file (``configs/stress/*.yaml``): a team, the team it is compared with, and
one-factor shifts beyond the training ranges, each judged at a declared value. What a file
says and how it runs: :mod:`mysim_jax.tasks.stress`. Pydantic only: validating a file
never imports JAX."""

from __future__ import annotations

import json
import re
from typing import Annotated, Literal

from pydantic import Field, ValidationError, model_validator

from mysim_jax.config.env import PerceptionConfig, RandomizeConfig
from mysim_jax.core.config_base import (ConfigError, Finite, NonNegFloat, StrictModel, format_validation_error,
                                        read_yaml_file)

SLUG = re.compile(r"^[a-z][a-z0-9_]*$")
NOMINAL = "nominal"


class StressFactor(StrictModel):
    """One shifted quantity (module docstring)."""

    name: Annotated[str, Field(pattern=SLUG.pattern, max_length=48)]   # also its output folder
    label: str                                  # axis label, with the unit
    kind: Literal["draw", "box", "perception_scale", "latency", "thrust_loss"]
    draw: str | None = None                     # env.randomize field (draw, box)
    axes: tuple[Finite, Finite, Finite] = (1.0, 1.0, 0.0)   # box: the axes the half-width spans
    values: Annotated[list[NonNegFloat], Field(min_length=1)]   # the shifted values, in the draw's unit
    judged_at: NonNegFloat                      # the value the criterion is judged at (one of values)
    fault_time: tuple[NonNegFloat, NonNegFloat] | None = None   # s, thrust_loss: when the fault starts

    @model_validator(mode="after")
    def _consistent(self):
        if self.kind in ("draw", "box"):
            if self.draw is None:
                raise ValueError(f"kind {self.kind} needs draw: the env.randomize field it shifts "
                                 f"({', '.join(RandomizeConfig.model_fields)})")
            if self.draw not in RandomizeConfig.model_fields:
                raise ValueError(f"draw {self.draw!r} is not an env.randomize field; the fields are "
                                 f"{', '.join(RandomizeConfig.model_fields)}")
            box = self.draw == "wind_force"
            if box != (self.kind == "box"):
                raise ValueError(f"draw {self.draw} is a {'box' if box else 'scalar'} range: write kind "
                                 f"{'box' if box else 'draw'}")
        elif self.draw is not None:
            raise ValueError(f"kind {self.kind} takes no draw")
        if (self.kind == "thrust_loss") != (self.fault_time is not None):
            raise ValueError("fault_time [low, high] (s) goes with kind thrust_loss, and only with it")
        if self.kind == "thrust_loss" and max(self.values) > 1.0:
            raise ValueError(f"thrust_loss values are the fraction of the thrust lost, at most 1: {self.values}")
        if self.judged_at not in self.values:
            raise ValueError(f"judged_at {self.judged_at:g} is not one of values {self.values}")
        if len(set(self.values)) != len(self.values):
            raise ValueError(f"values repeat: {self.values}")
        return self


class StressCriterion(StrictModel):
    """What a shift must keep, at each factor's ``judged_at`` (module docstring); unset: not judged."""

    fraction_of_nominal: Annotated[float, Field(gt=0, le=1)] | None = None
    lead_points: Finite | None = None           # paired difference policy - compare, points
    lead_low95_points: Finite | None = None     # its 95 % interval's lower end, points


class StressConfig(StrictModel):
    """A stress file (module docstring)."""

    name: Annotated[str, Field(pattern=SLUG.pattern, max_length=48)]
    scene: str                                  # the team's scene file (its training ranges)
    policy: str
    compare: str = "scripted"
    level: str = "train"
    episodes: Annotated[int, Field(ge=1)]
    batch: Annotated[int, Field(ge=1)] = 250
    seed: Annotated[int, Field(ge=0)]
    perception: str | None = None               # env.perception block file, for perception_scale
    set: list[str] = []                         # scene overrides (KEY=VALUE, as --set) of every point
    criterion: StressCriterion = StressCriterion()
    factors: Annotated[list[StressFactor], Field(min_length=1)]

    @model_validator(mode="after")
    def _consistent(self):
        names = [f.name for f in self.factors]
        if len(set(names)) != len(names) or NOMINAL in names:
            raise ValueError(f"factor names must be distinct and not {NOMINAL!r}: {names}")
        if any(f.kind == "perception_scale" for f in self.factors) and self.perception is None:
            raise ValueError("a perception_scale factor needs perception: the env.perception block file it scales")
        return self


def load_stress(path) -> StressConfig:
    """The validated stress file; ConfigError naming the file and every problem. No JAX."""
    data = read_yaml_file(path, "stress file")
    try:
        return StressConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"{path}: {format_validation_error(err)}") from None


def _flow(value) -> str:
    """A value as one line of YAML (JSON is YAML's flow style), numbers as Python prints them."""
    return json.dumps(value)


# the env.perception blocks a perception_scale factor scales (their sigma)
ERROR_BLOCKS = ("uav_position", "uav_velocity", "target_position", "target_velocity")


def perception_block(path) -> dict:
    """The env.perception block of a file (``scripts/perception_gap.py fit``'s output), validated."""
    data = read_yaml_file(path, "perception block")
    try:
        block = PerceptionConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"{path}: {format_validation_error(err)}") from None
    if (block.scale.low, block.scale.high) != (1.0, 1.0):
        raise ConfigError(f"{path}: scale {{low: {block.scale.low:g}, high: {block.scale.high:g}}}: a stress suite "
                          "sets the errors' scale itself (the perception factor's values); remove scale from the "
                          "block")
    return block.model_dump(exclude_none=True, exclude={"scale"})


def factor_override(factor: StressFactor, value: float, perception: dict | None = None) -> str:
    """The scene override (``KEY=VALUE``) that sets ``factor`` to ``value``."""
    if factor.kind == "draw":
        return f"env.randomize.{factor.draw}={_flow({'low': value, 'high': value})}"
    if factor.kind == "box":
        half = [value * a for a in factor.axes]
        return f"env.randomize.{factor.draw}={_flow({'low': [-h for h in half], 'high': half})}"
    if factor.kind == "latency":
        return f"env.perception={_flow({'target_latency': value})}"
    if factor.kind == "thrust_loss":
        lo, hi = factor.fault_time
        left = round(1.0 - value, 12)
        return (f"env.randomize.thrust_loss="
                f"{_flow({'fraction': {'low': left, 'high': left}, 'time': {'low': lo, 'high': hi}})}")
    if value == 0:
        return "env.perception=null"
    scaled = {k: {**perception[k], "sigma": perception[k]["sigma"] * value} for k in ERROR_BLOCKS if k in perception}
    for k in ("target_latency", "target_dropout"):      # the block's own latency and losses, unscaled
        if perception.get(k):
            scaled[k] = perception[k]
    return f"env.perception={_flow(scaled)}"


def training_range(config, factor: StressFactor) -> tuple[float, float] | None:
    """The factor's training range in the scene ``config`` (low, high in the factor's
    unit): the draw's range (a box: its largest half-width on the factor's axes), ``(0,
    0)`` for perception trained on true states, else the scene's ``env.perception.scale``
    range (1 when it is fixed);
    None when the scene does not draw it."""
    if factor.kind == "perception_scale":
        p = config.env.perception
        return (0.0, 0.0) if p is None else (p.scale.low, p.scale.high)
    if factor.kind == "latency":
        p = config.env.perception
        return (0.0, 0.0) if p is None else (p.target_latency, p.target_latency)
    if factor.kind == "thrust_loss":
        t = config.env.randomize.thrust_loss
        return (0.0, 0.0) if t is None else (1.0 - t.fraction.high, 1.0 - t.fraction.low)
    r = getattr(config.env.randomize, factor.draw)
    if r is None:
        return None
    if factor.kind == "box":
        half = max(max(abs(lo), abs(hi)) for lo, hi, a in zip(r.low, r.high, factor.axes) if a != 0)
        return (0.0, half)
    return (r.low, r.high)
