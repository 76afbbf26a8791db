"""Scene configuration: YAML files loaded into typed, validated configs.

``load_config(path, overrides)`` reads a YAML scene file, applies command-line overrides
(``sim.dt=5e-4``, ``ropes.0.EA=2e5``), and validates everything with pydantic before any
JAX code runs. Every problem is reported as a :class:`ConfigError` that names the field
(``ropes.0.EA: Input should be greater than 0``) and the file it came from.

Checks done here: the file itself (UTF-8 YAML text without duplicate keys, see
:mod:`mysim_jax.core.config_base`), unknown keys, wrong types or shapes, booleans where numbers
belong, numbers beyond the accepted range, non-positive masses / lengths / stiffnesses,
an output grid that does not fit the step (``output_dt`` a whole multiple of ``dt``,
``t_end`` of ``output_dt``), runs too long to be meant (:data:`MAX_ENV_STEPS`) and the
``effects:`` blocks of registered effects (:mod:`mysim_jax.config.effect_blocks`). The
checks across blocks are functions of the validated scene that :class:`SceneConfig` runs:
duplicate names, references (rope ends, spring ends, joint markers, loads) to things that
do not exist, contact pairs that list no pair and scenes too large to be meant
(:mod:`mysim_jax.config.scene_checks`), and the capture blocks'
(:mod:`mysim_jax.config.capture_checks`). Overrides are applied to the raw file by
:mod:`mysim_jax.config.overrides`. The explicit stability check needs the assembled
topology (masses on both ends of every spring), so it runs in
:func:`mysim_jax.build.build`, still before anything compiles, and reports against
``sim.dt`` / ``sim.substeps``.

Units are SI throughout. Quaternions are scalar-first ``[w, x, y, z]`` (normalised on
load; a zero quaternion is an error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import numpy as np
import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from mysim_jax.config.capture import TargetConfig, TeamConfig
from mysim_jax.config.capture_checks import capture_problems
from mysim_jax.config.effect_blocks import validate_effect_blocks
from mysim_jax.config.env import EnvConfig
from mysim_jax.config.overrides import apply_override, override_list, unaliased
from mysim_jax.config.quadrotor import QuadrotorConfig
from mysim_jax.config.scene_checks import reference_problems
from mysim_jax.contact.config import ContactConfig
from mysim_jax.core.config_base import (ConfigError, Finite, MIN_POSITIVE, Name, NonNegFloat, PosFloat, StrictModel,
                                        Tolerance, UnitQuat, Vec3, available_memory_bytes, format_validation_error,
                                        read_yaml_file)
from mysim_jax.net.config import NetConfig, net_elements

__all__ = ["ConfigError", "SceneConfig", "RunSettings", "load_config", "config_from_dict", "apply_override",
           "dump_config"]

INTEGRATORS = ("semi_implicit_euler", "rk4", "implicit_euler", "tsit5", "kvaerno5")
FIXED_STEP_INTEGRATORS = ("semi_implicit_euler", "rk4", "implicit_euler")
ADAPTIVE_INTEGRATORS = ("tsit5", "kvaerno5")

# Conjugate-gradient iterations per step of ``implicit_euler`` (sim.implicit_iterations):
# the default and the largest accepted. 20 keeps randomised nets stable up to 20x the
# explicit step (twice what ``substeps: auto`` takes; with 10 iterations a 44-mass net
# blows up at 20x) and solves the capture nets at their own step to a small relative residual
# (docs/scenes.md, "Stiff ropes at large steps", gives both measurements).
IMPLICIT_ITERATIONS = 20
MAX_IMPLICIT_ITERATIONS = 10_000

# Run-size limits: a run beyond these is almost always a typo (t_end in ms, dt in s...).
MAX_ENV_STEPS = 2**31 - 1          # environment steps of one run (the controller counts them in int32)
MAX_ROPE_MASSES = 10_000           # lumped masses of one rope
# output_dt / dt and t_end / output_dt must be whole numbers to this relative tolerance
GRID_TOLERANCE = 1e-6

Quat = tuple[Finite, Finite, Finite, Finite]


def check_output_memory(config, source: str, available: int | None = None) -> None:
    """Refuse, before anything compiles, a run whose saved outputs
    (:meth:`SceneConfig.output_memory_bytes`) exceed the memory the machine has."""
    available = available_memory_bytes() if available is None else available
    need = config.output_memory_bytes()
    if available is not None and need > available:
        rows, columns = config.output_size()
        raise ConfigError(f"{source}: sim: the run's saved outputs need about {need / 2**30:,.1f} GiB ({rows:,} rows "
                          f"of {columns:,} columns); this machine has {available / 2**30:,.1f} GiB available: "
                          "raise sim.output_dt or shorten sim.t_end")


@dataclass(frozen=True)
class RunSettings:
    """What one run of a scene saves: not part of the compiled Scene, so changing any of it
    (a longer run, another output interval, other plots) never recompiles the step.

    ``output_dt`` is a whole multiple of the step ``dt`` and ``t_end`` of ``output_dt``
    (:class:`SimConfig` checks and snaps them).
    """

    name: str
    t_end: float          # s
    output_dt: float      # s
    plot: tuple[str, ...] = ()

class BaumgarteConfig(StrictModel):
    """Baumgarte stabilisation of joint constraints: C̈ + 2·alpha·Ċ + beta²·C = 0.

    alpha [1/s] damps the velocity-level drift, beta [1/s] pulls the position error back.
    The defaults (critically damped, time constant 1/beta = 20 ms) keep drift small
    without stiffening the system beyond what a 1e-3 s step resolves.
    """

    alpha: NonNegFloat = 50.0
    beta: NonNegFloat = 50.0


# Smallest adaptive-solver tolerance accepted in float32. On the rope net, float32 tsit5
# runs at rtol = atol = 1e-6 and at rtol 1e-5 / atol 1e-6, but atol 1e-7 (or the float64
# defaults) exhausts max_steps (the error estimate is round-off noise).
FLOAT32_MIN_TOLERANCE = 1e-6


class SmoothBackwardConfig(StrictModel):
    """The tension-only line law smoothed in the backward pass only (``sim.smooth_backward``).

    The forward pass keeps the exact law, ``T = max(k (l - l0) + c dl/dt, 0)`` while the
    line is longer than at rest, else 0; reverse-mode gradients (``jax.grad``, ``jax.vjp``)
    are those of ``tension * softplus(T_lin / tension) * sigmoid((l - l0) / slack)``, with
    ``T_lin = k (l - l0) + c dl/dt``: the slack/taut switch spread over ``slack`` metres of
    stretch and the zero-tension kink over ``tension`` newtons. A line switching between
    slack and taut then no longer multiplies the backward pass at every switch
    (docs/gradients.md). Nothing a simulation computes changes; forward-mode derivatives
    (``jax.jvp``) are not defined with it."""

    tension: PosFloat        # N, width of the zero-tension kink in the backward pass
    slack: PosFloat          # m, width of the slack/taut switch in the backward pass


class SimConfig(StrictModel):
    """Time integration settings.

    ``dt`` is the environment step (controls are held over it); the integrator advances
    it in ``substeps`` equal sub-steps of ``dt / substeps`` (fixed-step integrators), or
    adaptively with ``rtol``/``atol`` starting from ``dt / substeps`` (diffrax solvers).
    ``substeps: auto`` lets :func:`mysim_jax.build.build` choose the number of sub-steps
    from the explicit stability limits: the spring network's accepted step, half the
    per-element limits of contact pairs and Baumgarte terms (1 for the adaptive solvers).

    ``output_dt`` must be a whole multiple of ``dt`` and ``t_end`` a whole multiple of
    ``output_dt`` (to a relative 1e-6; the run then uses the exact multiples,
    :attr:`output_every` steps per output and :attr:`n_outputs` outputs after the
    initial state), so that the run covers exactly ``t_end`` and every saved row lies
    on a step.
    """

    t_end: PosFloat
    dt: PosFloat
    substeps: Union[Annotated[int, Field(ge=1, le=1_000_000)], Literal["auto"]] = 1
    output_dt: PosFloat
    integrator: Literal["semi_implicit_euler", "rk4", "implicit_euler", "tsit5", "kvaerno5"] = "semi_implicit_euler"
    precision: Literal["float32", "float64"] = "float32"
    rtol: Tolerance = 1e-8
    atol: Tolerance = 1e-10
    max_steps: Annotated[int, Field(ge=1, le=2**31 - 1)] = 10_000_000
    # conjugate-gradient iterations per step of implicit_euler (None: IMPLICIT_ITERATIONS)
    implicit_iterations: Optional[Annotated[int, Field(ge=1, le=MAX_IMPLICIT_ITERATIONS)]] = None
    # how the force pipeline sums node forces and gathers spring ends: the same physics to
    # float round-off, at different speeds per backend (BENCHMARKS.md, sections b and j)
    accumulate: Literal["segment_sum", "matmul"] = "segment_sum"
    gather: Literal["slices", "index"] = "slices"
    # reverse-mode gradients of the tension-only lines taken from a smoothed law, the
    # forward pass unchanged (SmoothBackwardConfig; None: the exact law's gradients)
    smooth_backward: Optional[SmoothBackwardConfig] = None

    @property
    def cg_iterations(self) -> int:
        """CG iterations per step the built scene uses (0 unless ``implicit_euler``)."""
        if self.integrator != "implicit_euler":
            return 0
        return IMPLICIT_ITERATIONS if self.implicit_iterations is None else self.implicit_iterations

    @model_validator(mode="after")
    def _implicit_iterations_need_implicit_euler(self):
        if self.implicit_iterations is not None and self.integrator != "implicit_euler":
            raise ValueError(
                f"implicit_iterations = {self.implicit_iterations} is a setting of integrator: implicit_euler, "
                f"not of {self.integrator}: remove it or use integrator: implicit_euler")
        if self.smooth_backward is not None and self.integrator == "implicit_euler":
            raise ValueError("smooth_backward smooths the explicit spring forces' gradients; implicit_euler solves "
                             "its springs apart: remove smooth_backward or use an explicit integrator")
        return self

    @property
    def output_every(self) -> int:
        """Environment steps between saved states (``output_dt / dt``, a whole number)."""
        return max(1, round(self.output_dt / self.dt))

    @property
    def n_outputs(self) -> int:
        """Saved states after the initial one (``t_end / output_dt``, a whole number)."""
        return round(self.t_end / (self.output_every * self.dt))

    @model_validator(mode="after")
    def _float32_tolerances(self):
        if self.precision == "float32" and self.integrator in ("tsit5", "kvaerno5"):
            for key, value in (("atol", self.atol), ("rtol", self.rtol)):
                if value < FLOAT32_MIN_TOLERANCE:
                    raise ValueError(
                        f"{key} = {value:g} is below what float32 resolves (round-off ~1e-7 on "
                        "metre-scale coordinates): the adaptive solver would shrink its step "
                        f"until max_steps. Use rtol and atol >= {FLOAT32_MIN_TOLERANCE:g} in "
                        "float32 (e.g. 1e-5), or precision: float64"
                    )
        return self

    @model_validator(mode="after")
    def _grid(self):
        ratio = self.output_dt / self.dt
        if ratio < 1.0 - GRID_TOLERANCE:
            raise ValueError(f"output_dt ({self.output_dt:g}) is shorter than dt ({self.dt:g}): "
                             "states are saved on environment steps")
        if abs(ratio - round(ratio)) > GRID_TOLERANCE * ratio:
            lo = max(1, math.floor(ratio)) * self.dt
            raise ValueError(
                f"output_dt ({self.output_dt:g}) must be a whole multiple of dt ({self.dt:g}); "
                f"e.g. {lo:g} or {lo + self.dt:g}"
            )
        grid = self.output_every * self.dt
        runs = self.t_end / grid
        if runs < 1.0 - GRID_TOLERANCE:
            raise ValueError(
                f"t_end ({self.t_end:g} s) is shorter than one output interval ({grid:g} s): the run "
                "would save nothing but its initial state"
            )
        if abs(runs - round(runs)) > GRID_TOLERANCE * runs:
            lo = math.floor(runs) * grid
            raise ValueError(
                f"t_end ({self.t_end:g} s) must be a whole multiple of output_dt ({grid:g} s) so "
                f"that the run ends on a saved state; e.g. {lo:g} or {lo + grid:g}"
            )
        steps = self.n_outputs * self.output_every
        if steps > MAX_ENV_STEPS:
            raise ValueError(
                f"t_end / dt = {steps:.3g} environment steps: more than {MAX_ENV_STEPS:,} "
                "(check the units of t_end and dt)"
            )
        return self


class PointConfig(StrictModel):
    """A point mass (no orientation)."""

    name: Name
    mass: PosFloat
    pos: Vec3 = (0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)


class MarkerConfig(StrictModel):
    """A local frame on a rigid body: offset ``pos`` and orientation ``quat`` (body frame)."""

    name: Name
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: UnitQuat = (1.0, 0.0, 0.0, 0.0)


Inertia = Union[Vec3, tuple[Vec3, Vec3, Vec3]]


class BodyConfig(StrictModel):
    """A rigid body. ``inertia`` about the centre of mass, body frame: diagonal [Ixx, Iyy, Izz]
    or a full symmetric 3x3 matrix. ``vel`` is world-frame, ``angvel`` body-frame."""

    name: Name
    mass: PosFloat
    inertia: Inertia
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: UnitQuat = (1.0, 0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)
    markers: list[MarkerConfig] = []

    @field_validator("inertia")
    @classmethod
    def _inertia(cls, v):
        m = np.diag(v) if len(v) == 3 and not isinstance(v[0], tuple) else np.array(v, dtype=float)
        if not np.allclose(m, m.T, rtol=1e-9, atol=1e-15):
            raise ValueError("inertia matrix must be symmetric")
        eig = np.linalg.eigvalsh(m)
        if eig.min() <= 0:
            raise ValueError(f"inertia must be positive definite (eigenvalues {[float(e) for e in eig]})")
        if eig.min() < MIN_POSITIVE:
            raise ValueError(f"smallest principal moment {float(eig.min()):g} kg m^2 is below {MIN_POSITIVE:g}: "
                             "the angular accelerations it gives overflow float32")
        a, b, c = sorted(eig)
        if c > a + b + 1e-12 * c:
            raise ValueError(
                f"principal moments {[float(a), float(b), float(c)]} violate the triangle inequality "
                "(no physical mass distribution has them)"
            )
        return v


class AnchorConfig(StrictModel):
    """A fixed world frame: rope / spring ends attach to it, joints can use it as a marker."""

    name: Name
    pos: Vec3
    quat: UnitQuat = (1.0, 0.0, 0.0, 0.0)


class RopeConfig(StrictModel):
    """A lumped-mass rope (paper Sec. 2.1): ``n_masses`` point masses of ``mass`` each,
    rest length ``length / n_masses`` between interior masses and half that at both ends.
    ``n_masses: 0`` is one spring-damper segment of rest length ``length`` between the two
    ends (no mass of its own: whoever lumps the line's mass puts it on the ends).

    ``start`` / ``end`` name a point, an anchor, a body (its centre) or ``body.marker``.
    ``model: tension_only`` (default) never pushes; ``linear`` is the two-way spring-damper
    the paper uses for validation. The masses start on the straight line between the two
    ends, at their rest spacing scaled to the current end-to-end distance.
    """

    name: Name
    length: PosFloat
    n_masses: Annotated[int, Field(ge=0, le=MAX_ROPE_MASSES)]
    mass: PosFloat
    EA: PosFloat
    damping: NonNegFloat = 0.0
    model: Literal["tension_only", "linear"] = "tension_only"
    start: str
    end: str


class SpringConfig(StrictModel):
    """A spring-damper between two attachment points (same references as rope ends).
    ``rest_length`` defaults to the initial distance."""

    name: Name
    start: str
    end: str
    stiffness: PosFloat
    damping: NonNegFloat = 0.0
    rest_length: NonNegFloat | None = None
    model: Literal["tension_only", "linear"] = "linear"


class JointConfig(StrictModel):
    """A joint between two markers (``body.marker`` or an anchor name), paper Appendix A.

    fixed: r_I = r_J, x_I·y_J = x_I·z_J = y_I·z_J = 0.
    universal: r_I = r_J, z_I·z_J = 0.
    """

    name: Name
    type: Literal["fixed", "universal"]
    marker_i: str
    marker_j: str


class LoadConfig(StrictModel):
    """A constant applied load: ``force`` (world frame, N) at a point, body centre, or
    ``body.marker``; ``torque`` (body frame, N·m) on a body."""

    at: str
    force: Vec3 = (0.0, 0.0, 0.0)
    torque: Vec3 = (0.0, 0.0, 0.0)


class OutputConfig(StrictModel):
    """What ``scripts/simulate.py`` plots (names of points or bodies)."""

    plot: list[str] = []


class LevelConfig(StrictModel):
    """A named fidelity level of a scene: plain scene values (``dotted.key=value``, as
    ``--set`` takes them) applied over the file's own, which are the level ``full``."""

    description: str = ""
    # empty in a resolved file (dump_config), whose own values are the level's already
    set: list[str]
    # true in a resolved file: its own values are this level's, not the level full's, so
    # no other level can be loaded from it
    resolved: bool = False


FULL_LEVEL = "full"
"""The level a scene file's own values are; other levels are listed under ``levels:``."""


class SceneConfig(StrictModel):
    """A whole scene, as written in ``configs/*.yaml``.

    ``levels`` names cheaper (or finer) versions of the scene, each a list of scene values
    over the file's own (the level ``full``); ``level`` picks one when the file is loaded
    (``--set level=train``): its values are applied first, then the other overrides.
    """

    name: Name
    description: str = ""
    level: Name = FULL_LEVEL                 # the fidelity level this config was loaded at
    levels: dict[Name, LevelConfig] = {}
    sim: SimConfig
    gravity: Vec3 = (0.0, 0.0, -9.81)
    baumgarte: BaumgarteConfig = BaumgarteConfig()
    points: list[PointConfig] = []
    bodies: list[BodyConfig] = []
    anchors: list[AnchorConfig] = []
    ropes: list[RopeConfig] = []
    springs: list[SpringConfig] = []
    joints: list[JointConfig] = []
    loads: list[LoadConfig] = []
    output: OutputConfig = OutputConfig()
    contact: ContactConfig | None = None     # see mysim_jax/contact/config.py
    quadrotors: list[QuadrotorConfig] = []   # see mysim_jax/config/quadrotor.py
    net: NetConfig | None = None             # see mysim_jax/net/config.py
    target: TargetConfig | None = None       # see mysim_jax/config/capture.py
    team: TeamConfig | None = None           # see mysim_jax/config/capture.py
    env: EnvConfig | None = None             # see mysim_jax/config/env.py
    effects: dict[Name, Any] = {}            # registered effects' own blocks, see mysim_jax/config/effect_blocks.py

    @field_validator("effects")
    @classmethod
    def _effect_blocks(cls, blocks):
        return validate_effect_blocks(blocks)

    @model_validator(mode="after")
    def _references(self):
        # the net and the target are checked as what they expand to (points, ropes, a body)
        full, problems = expand_capture(self)
        problems += reference_problems(full)
        problems += capture_problems(self)
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # --- name tables -------------------------------------------------------------------
    def anchor_names(self) -> set[str]:
        return {a.name for a in self.anchors}

    def marker_names(self) -> set[str]:
        return {f"{b.name}.{m.name}" for b in self.bodies for m in b.markers}

    def frame_names(self) -> set[str]:
        """Names a joint may use: ``body.marker`` and anchors."""
        return self.marker_names() | self.anchor_names()

    def output_size(self) -> tuple[int, int]:
        """``(rows, columns)`` of the trajectory a run of this file saves, as
        scripts/simulate.py writes it (:mod:`mysim_jax.io.trajectory`)."""
        n_points = len(self.points) + sum(r.n_masses for r in self.ropes)
        n_bodies = len(self.bodies) + sum(len(q.cameras) for q in self.quadrotors)
        return self.sim.n_outputs + 1, 1 + 9 * n_points + 16 * n_bodies + 8 * len(self.quadrotors)

    def output_memory_bytes(self) -> int:
        """An estimate of the memory a run's saved outputs take at once: every saved value
        at the scene's precision as the run returns it, and again as the float64 column
        written to the CSV file."""
        rows, columns = self.output_size()
        return rows * columns * ((8 if self.sim.precision == "float64" else 4) + 8)

    def run_settings(self) -> RunSettings:
        """The run settings of this scene file (exact multiples of ``sim.dt``)."""
        sim = self.sim
        return RunSettings(name=self.name, t_end=sim.n_outputs * sim.output_every * sim.dt,
                           output_dt=sim.output_every * sim.dt, plot=tuple(self.output.plot))

    def trajectory_names(self) -> set[str]:
        """Points (including rope masses) and bodies: the things that move."""
        names = {p.name for p in self.points} | {b.name for b in self.bodies}
        names |= {c.name for q in self.quadrotors for c in q.cameras}
        for r in self.ropes:
            names |= {f"{r.name}_{j}" for j in range(r.n_masses)}
        return names

    def attachment_names(self) -> set[str]:
        """Names a rope / spring end may use."""
        return self.trajectory_names() | self.marker_names() | self.anchor_names()


# --- capture scenes: the net and the target as ordinary entries -------------------------


def expand_capture(config: SceneConfig) -> tuple[SceneConfig, list[str]]:
    """``(config with the net's knots, ropes and tether markers and the target's body
    added, problems)``. The input is not touched (the expanded copy is not re-validated:
    the caller checks it). Without ``net:`` and ``target:`` the config comes back as is."""
    if config.net is None and config.target is None:
        return config, []
    problems: list[str] = []
    points, ropes, bodies = list(config.points), list(config.ropes), list(config.bodies)
    if config.net is not None:
        by_name = {b.name: b for b in config.bodies}
        elements = net_elements(config.net, by_name, {q.body for q in config.quadrotors} & set(by_name))
        problems += elements.problems
        points += [PointConfig.model_construct(vel=(0.0, 0.0, 0.0), **p) for p in elements.points]
        ropes += [RopeConfig.model_construct(**r) for r in elements.ropes]
        bodies = [b.model_copy(update={"markers": list(b.markers) + [MarkerConfig.model_construct(
                      quat=(1.0, 0.0, 0.0, 0.0), **elements.markers[b.name])]})
                  if b.name in elements.markers else b for b in bodies]
    if config.target is not None:
        t = config.target
        spawn = t.spawn
        bodies.append(BodyConfig.model_construct(
            name=t.name, mass=t.mass, inertia=t.inertia,
            pos=tuple(0.5 * (lo + hi) for lo, hi in zip(spawn.position.low, spawn.position.high)),
            quat=(1.0, 0.0, 0.0, 0.0),
            vel=tuple(0.5 * (lo + hi) for lo, hi in zip(spawn.velocity.low, spawn.velocity.high)),
            angvel=(0.0, 0.0, 0.0), markers=[]))
    expanded = config.model_copy(update={"points": points, "ropes": ropes, "bodies": bodies,
                                         "net": None, "target": None, "team": None,
                                         "env": None})
    return expanded, problems


# --- loading ---------------------------------------------------------------------------


def config_from_dict(raw: Any, source: str = "<dict>", overrides: list[str] | tuple[str, ...] = (),
                     check_levels: bool = True) -> SceneConfig:
    """Validate a raw (YAML-parsed) dict into a :class:`SceneConfig` (at the ``level`` the
    overrides or the file pick; with ``check_levels`` every other level of the file is
    validated too, so a broken level is reported whichever level is loaded)."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: a scene file must be a YAML mapping at the top level")
    original = raw
    config = _config_at_level(raw, source, overrides)
    if check_levels:
        for name in config.levels:
            if name != config.level:
                try:
                    _config_at_level(original, source, override_list(level=name))
                except ConfigError as err:
                    raise ConfigError(f"{source}: levels.{name}: the level does not load:\n{err}") from None
    return config


def _config_at_level(raw: dict, source: str, overrides) -> SceneConfig:
    raw = unaliased(raw)
    levels_raw = raw.get("levels")
    if levels_raw is not None and not isinstance(levels_raw, dict):
        raise ConfigError(f"{source}: levels: expected a mapping of level name -> "
                          f"{{description, set: [dotted.key=value, ...]}}, got {type(levels_raw).__name__}")
    if FULL_LEVEL in (levels_raw or {}):
        raise ConfigError(f"{source}: levels.{FULL_LEVEL}: '{FULL_LEVEL}' is the file's own values; "
                          "name the level otherwise")
    chosen = unaliased(raw)
    for ov in overrides:
        apply_override(chosen, ov)
    level = chosen.get("level", FULL_LEVEL)
    if not isinstance(level, str):
        raise ConfigError(f"{source}: level: expected the name of a fidelity level, got {level!r}")
    _check_not_resolved_elsewhere(raw, level, source)
    if level != FULL_LEVEL:
        levels = raw.get("levels") or {}
        if not isinstance(levels, dict) or level not in levels:
            known = ", ".join([FULL_LEVEL] + sorted(levels if isinstance(levels, dict) else ()))
            raise ConfigError(f"{source}: level: unknown fidelity level '{level}' (this file has: {known})")
        entry = levels[level]
        sets = entry.get("set") if isinstance(entry, dict) else None
        if not isinstance(sets, list) or not all(isinstance(v, str) for v in sets):
            raise ConfigError(f"{source}: levels.{level}.set: expected a list of 'dotted.key=value' strings")
        for ov in sets:
            if ov.split("=", 1)[0].strip().split(".")[0] in ("level", "levels"):
                raise ConfigError(f"{source}: levels.{level}.set: '{ov}': a level cannot set level or levels")
            try:
                apply_override(raw, ov)
            except ConfigError as err:
                raise ConfigError(f"{source}: levels.{level}.set: {err}") from None
    for ov in overrides:
        apply_override(raw, ov)
    try:
        return SceneConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(f"{source}: invalid scene configuration\n{format_validation_error(err)}") from None


def _check_not_resolved_elsewhere(raw: dict, level: str, source: str) -> None:
    """A resolved file (``dump_config`` at a level other than ``full``: a run folder's
    ``scene.yaml``) holds one level's values as its own; asking it for another level would
    load those values under the other level's name, so it is an error."""
    own, levels = raw.get("level", FULL_LEVEL), raw.get("levels")
    if not (isinstance(own, str) and isinstance(levels, dict)):     # malformed: validation names it
        return
    entry = levels.get(own)
    if level != own and isinstance(entry, dict) and entry.get("resolved") is True:
        raise ConfigError(
            f"{source}: level={level}: this file is resolved at the level '{own}' (its own values are that "
            f"level's, as a run folder's scene.yaml is), so it cannot give the level '{level}'. Load the "
            f"original scene file with --set level={level}, or a run folder's scene_eval.yaml for the level "
            "its evaluation ran at.")


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> SceneConfig:
    """Read, override and validate a YAML scene file. Raises :class:`ConfigError` naming
    the file and the field (:mod:`mysim_jax.core.config_base` lists what a file may not be)."""
    return config_from_dict(read_yaml_file(path, "config file"), str(path), overrides)


def dump_config(config: SceneConfig) -> str:
    """The resolved config as YAML (round-trips through :func:`config_from_dict`). At a
    level other than ``full`` the level's values are the file's own values in the dump:
    it keeps ``level: NAME`` with an empty ``levels.NAME.set`` and ``resolved: true`` (so it
    reloads as it is, under the level's name, and refuses to give another level) and drops
    the other levels, which were relative to the original file."""
    data = config.model_dump(mode="json")
    if not data["effects"]:        # a file without effect blocks dumps as it did before they existed
        del data["effects"]
    if data["level"] != FULL_LEVEL:
        name = data["level"]
        entry = data["levels"][name]
        description = entry["description"] if entry["resolved"] else (
            f"{entry['description']} (resolved: the values above are this level's)".strip())
        data["levels"] = {name: {"description": description, "set": [], "resolved": True}}
    return yaml.safe_dump(data, sort_keys=False)
