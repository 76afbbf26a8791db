"""The ``target:`` and ``team:`` blocks of a capture scene file.

``target:`` is a non-cooperative target: a rigid sphere (a body named ``name``) with
mass, radius and quadratic air drag. ``behaviour: falling`` releases it from a spawn
drawn from ranges and lets it fall; ``behaviour: maneuvering`` gives it its own bounded
propulsion under an evasive behaviour the team does not know (:mod:`mysim_jax.effects.target`).
Every random draw (spawn position and velocity, jinks) comes from a PRNG key seeded with
``seed`` and carried in the State, so a run is reproducible from its seed.

``team:`` selects who gives the quadrotors their setpoints in ``scripts/simulate.py``:
``scripted`` is the intercept team of :mod:`mysim_jax.tasks.scripted` (fly the net under
the predicted path of the target).

Pydantic and NumPy only: validating a file never imports JAX.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import Field, model_validator

from mysim_jax.core.config_base import Finite, Name, NonNegFloat, PosFloat, StrictModel, Vec3


class BoxRange(StrictModel):
    """A box of vectors ``low <= v <= high`` (per axis) from which a value is drawn
    uniformly. ``low == high`` on an axis fixes that component."""

    low: Vec3
    high: Vec3

    @model_validator(mode="after")
    def _ordered(self):
        bad = [axis for axis, lo, hi in zip("xyz", self.low, self.high) if lo > hi]
        if bad:
            raise ValueError(f"empty range: low > high on axis {', '.join(bad)} "
                             f"(low {list(self.low)}, high {list(self.high)})")
        return self


class Range(StrictModel):
    """A scalar range ``low <= v <= high``, drawn uniformly (``low == high`` fixes it)."""

    low: NonNegFloat
    high: NonNegFloat

    @model_validator(mode="after")
    def _ordered(self):
        if self.low > self.high:
            raise ValueError(f"empty range: low ({self.low:g}) > high ({self.high:g})")
        return self


class IntervalRange(Range):
    """A range of time intervals ``0 < low <= v <= high`` [s]."""

    low: PosFloat
    high: PosFloat


class SpawnConfig(StrictModel):
    """Where and how fast the target starts (world frame): uniform draws from the boxes.

    ``clearance`` (m, 0: none) keeps the spawn that far horizontally from the quadrotors'
    centroid, under which the net hangs: an evader that starts under or in the net is
    caught before the task begins. A position drawn closer is drawn again (up to
    :data:`~mysim_jax.effects.target.SPAWN_TRIES` draws in all, which keeps the draw uniform
    over the allowed part of the box unless that part is tiny; the last draw, if it is
    still too close, is pushed straight out to the clearance). The value is a traced
    parameter (``TargetParams.spawn_clearance``, sweepable), but a scene built with 0 has
    no check at all: sweep it from a scene built with a positive clearance."""

    position: BoxRange
    velocity: BoxRange = BoxRange(low=(0.0, 0.0, 0.0), high=(0.0, 0.0, 0.0))
    clearance: NonNegFloat = 0.0


class PropulsionConfig(StrictModel):
    """Bounded propulsion of a maneuvering target (an evading drone).

    Its commanded acceleration (on top of what cancels gravity) is limited to
    ``max_acceleration`` and its speed to ``max_speed``. The evasive behaviour flees the
    team's centroid with ``flee_acceleration``, adds a random horizontal jink of
    ``jink_acceleration`` redrawn every ``jink_interval`` seconds, and holds its altitude
    inside ``altitude`` (a band it prefers).

    ``arena`` (optional) is the protected volume the intruder evades within: a box its
    centre stays inside. Near a wall the behaviour brakes toward the inside, at full
    acceleration once its stopping distance (at half ``max_acceleration``) reaches the
    wall, blending in over the last ``wall_margin`` metres before that. Without an arena
    the target may flee without bound.
    """

    max_acceleration: PosFloat = 4.0       # m/s^2
    max_speed: PosFloat = 3.0              # m/s
    flee_acceleration: NonNegFloat = 2.0   # m/s^2
    jink_acceleration: NonNegFloat = 3.0   # m/s^2
    jink_interval: IntervalRange = IntervalRange(low=0.4, high=1.2)
    altitude: tuple[PosFloat, PosFloat] = (2.0, 6.0)    # m
    altitude_gain: PosFloat = 2.0          # 1/s^2 toward the band, with critical damping
    arena: BoxRange | None = None          # m, world frame: the box the target's centre stays in
    wall_margin: PosFloat = 0.5            # m, over which the braking at a wall blends in

    @model_validator(mode="after")
    def _band(self):
        problems = []
        if self.altitude[0] > self.altitude[1]:
            problems.append(f"altitude: empty band {list(self.altitude)} (low > high)")
        if self.arena is not None:
            flat = [axis for axis, lo, hi in zip("xyz", self.arena.low, self.arena.high) if hi - lo <= 2 * self.wall_margin]
            if flat:
                problems.append(f"arena: no wider than twice wall_margin ({2 * self.wall_margin:g} m) on axis "
                                f"{', '.join(flat)} (low {list(self.arena.low)}, high {list(self.arena.high)}): the "
                                "target would brake everywhere: widen the arena or lower wall_margin")
            lo, hi = self.arena.low[2], self.arena.high[2]
            if not problems and not (lo <= self.altitude[0] and self.altitude[1] <= hi):
                problems.append(f"altitude: the band {list(self.altitude)} m is not inside the arena's heights "
                                f"({lo:g} to {hi:g} m, propulsion.arena)")
        if problems:
            raise ValueError("; ".join(problems))
        return self


class EntanglementConfig(StrictModel):
    """An evading drone's rotors tangle in the net's lines (:mod:`mysim_jax.effects.entanglement`):
    while its centre is within its radius plus ``margin`` of a line, it loses its
    propulsion at ``1 / time`` per second, for good."""

    time: PosFloat = 0.2                   # s of line contact for a full loss of propulsion
    margin: NonNegFloat = 0.02             # m the rotors reach beyond the target's radius


class TargetConfig(StrictModel):
    """A non-cooperative target: a rigid sphere (module docstring).

    Defaults: a 0.3 kg sphere of 15 cm radius (the size and weight of a small quadrotor
    with its propellers; its 30 cm diameter is wider than the default net's 20 cm mesh
    and its cells' 28 cm diagonal, so it cannot pass through a cell), drag coefficient
    0.47 (a sphere at these Reynolds numbers), sea-level air.
    """

    name: Name = "target"
    mass: PosFloat = 0.3                    # kg
    radius: PosFloat = 0.15                 # m
    drag_coefficient: NonNegFloat = 0.47
    air_density: NonNegFloat = 1.225       # kg/m^3
    behaviour: Literal["falling", "maneuvering"] = "falling"
    spawn: SpawnConfig
    propulsion: PropulsionConfig | None = None
    entanglement: EntanglementConfig | None = None   # None: line contact leaves its propulsion whole
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0

    @model_validator(mode="after")
    def _check(self):
        problems = []
        if self.spawn.position.low[2] < self.radius:
            problems.append(
                f"spawn.position.low: z = {self.spawn.position.low[2]:g} m puts the target below the ground "
                f"(its centre must be at least its radius, {self.radius:g} m, above z = 0)")
        if self.behaviour == "falling" and self.propulsion is not None:
            problems.append("propulsion: a falling target has no propulsion (use behaviour: maneuvering)")
        if self.behaviour == "falling" and self.entanglement is not None:
            problems.append("entanglement: a falling target has no rotors to entangle (use behaviour: maneuvering)")
        arena = self.propulsion.arena if self.propulsion is not None else None
        if arena is not None:
            outside = [axis for axis, slo, shi, alo, ahi in zip("xyz", self.spawn.position.low, self.spawn.position.high,
                                                                arena.low, arena.high) if slo < alo or shi > ahi]
            if outside:
                problems.append(f"spawn.position: the box (low {list(self.spawn.position.low)}, high "
                                f"{list(self.spawn.position.high)}) reaches outside propulsion.arena (low "
                                f"{list(arena.low)}, high {list(arena.high)}) on axis {', '.join(outside)}")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    @property
    def inertia(self) -> tuple[float, float, float]:
        """Solid sphere ``2/5 m r²`` [kg m²]."""
        j = 0.4 * self.mass * self.radius ** 2
        return (j, j, j)

    @property
    def drag_constant(self) -> float:
        """``½ ρ C_d π r²`` [kg/m]: the drag force is ``−drag_constant |v| v``."""
        return 0.5 * self.air_density * self.drag_coefficient * math.pi * self.radius ** 2

    def propulsion_or_default(self) -> PropulsionConfig | None:
        if self.behaviour == "maneuvering":
            return self.propulsion or PropulsionConfig()
        return None


class TeamConfig(StrictModel):
    """Who gives the quadrotors their setpoints when ``scripts/simulate.py`` runs the scene.

    ``scripted``: the intercept team (:mod:`mysim_jax.tasks.scripted`): it predicts where
    the target crosses the net's height, flies the formation so that the net's centre is
    there, ``lead`` seconds of the target's horizontal motion ahead, and lets the net
    give way (``soften``) once the target is in it. With velocity setpoints it is the
    velocity team of that module (drag-aware catch point, lag feed-forward, following the
    net after the catch: ``gain``, ``lag_gain``, ``follow_gain``). ``chase`` (velocity
    setpoints, an evading target): velocity feed-forward pursuit that flies the net
    ``standoff`` below the target while its centre is ``climb_radius`` or more from it
    horizontally and ``approach`` below once within ``close``, which only closes in on a
    far target once its UAVs are ``dive_gap`` below it, never commands the formation under
    ``min_altitude``, and holds ``altitude`` once the target is in the net (``ChaseTeam``;
    ``lead``, ``lag_gain`` as above, the gap closed at ``pursuit_gain``, the UAVs kept in
    formation at ``gain``). ``hold``: the team holds its start formation.
    """

    policy: Literal["scripted", "chase", "hold"] = "scripted"
    lead: NonNegFloat = 0.0                 # s
    soften: NonNegFloat = 0.3               # m the formation descends after the catch
    catch_radius: PosFloat = 0.6            # m: the target counts as "in the net" within this of its centre
    altitude: Finite | None = None          # m, formation height (default: the start height)
    # velocity setpoints only (mysim_jax/tasks/scripted.py, VelocityTeam)
    gain: PosFloat = 2.0                    # 1/s, commanded velocity per metre of position error
    lag_gain: NonNegFloat = 0.5             # -, extra speed per m/s by which the net trails the team
    follow_gain: NonNegFloat = 1.0          # 1/s, after the catch: velocity per metre the net is off centre
    # chase only (an evading target, velocity setpoints; mysim_jax/tasks/scripted.py, ChaseTeam)
    pursuit_gain: PosFloat = 0.7            # 1/s, velocity per metre of horizontal gap to the led target
    approach: Finite = -0.5                 # m, the net's mean height below the target's centre, close
    standoff: Finite = 2.0                  # m, the same while the net is far from under it
    close: PosFloat = 0.3                   # m, horizontal distance of net centre to target that counts as close
    climb_radius: PosFloat = 1.2            # m, beyond this horizontal distance the net flies standoff below
    dive_gap: NonNegFloat = 0.3             # m, UAVs this far below a far target before the team closes in
    min_altitude: NonNegFloat = 2.0         # m, the lowest formation height the chase commands

    @model_validator(mode="after")
    def _chase_radii(self):
        if self.policy == "chase" and self.climb_radius <= self.close:
            raise ValueError(f"team.climb_radius: {self.climb_radius:g} m must be larger than team.close "
                             f"({self.close:g} m): the net climbs from standoff to approach between the two")
        return self
