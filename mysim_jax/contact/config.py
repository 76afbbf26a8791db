"""The ``contact:`` block of a scene file (validated with the rest of the scene).

Example (the paper's collision scene, Table collision_module)::

    contact:
      model: sharp              # sharp: the paper's law; smooth: for gradients
      stiffness: 1.0e8          # k   [N/m^n]
      exponent: 1.0             # n   (>= 1)
      damping: 1.0e4            # c   [N s/m], reached at penetration damping_depth
      damping_depth: 1.0e-4     # p   [m]
      friction: {mu_static: 0.04, mu_dynamic: 0.03, v_static: 0.01, v_dynamic: 0.1}
      groups:                   # every member carries a sphere of the group's radius
        - {name: ball, members: [ball], radius: 0.03}
        - {name: payload, members: [payload], radius: 0.03}
        - {name: net, members: ["r?_*"], radius: 0.03}
      pairs:                    # which groups touch which; "ground" is the plane z = 0
        - [ball, payload]
        - [ball, net]

Members are names of point masses (rope masses included, ``r0_3``) or rigid bodies, or
shell-style patterns of them (``r?_*``, ``fnmatch`` rules). A pair ``[A, B]`` lists every
member of A against every member of B (an object never touches itself; a pair declared
twice is kept once); ``[A, A]`` lists each pair of A's members once; ``[A, ground]`` puts
A's spheres on the ground plane. Everything is resolved when the config is loaded, so a
misspelt group or a pattern that matches nothing is an error naming the field.

Capsules on rope segments
-------------------------
A group has either ``members`` (spheres) or ``segments``: names or patterns of ropes and
springs (scene names, ``net*``, ``tether_0``). Every segment of a matched rope (its
``n_masses + 1`` springs, ``rope[j]`` in the built scene) and every matched spring becomes
a *capsule*: the points within ``radius`` of the straight segment between its two end
nodes. A net whose masses sit further apart than a target is wide thus still stops it::

      groups:
        - {name: ball, members: [ball], radius: 0.03}
        - {name: mesh, segments: ["r?"], radius: 0.005}   # every segment of ropes r0..r9
      pairs:
        - [ball, mesh]                                     # or [mesh, ball]

A pair of a sphere group and a segment group lists every sphere against every capsule,
except a sphere on one of the capsule's own end nodes (a rope mass never touches its own
segments; a body's sphere never touches a segment attached to one of its markers).
Capsule–capsule and capsule–ground pairs are not modelled and are errors: ground contact
of a net goes through spheres on its masses (a ``members`` group paired with ``ground``).
The force law is the sphere pairs' (:mod:`mysim_jax.contact.forces`).

``friction`` is left out (or ``null``) for frictionless contact. ``smoothing`` is used by
``model: smooth`` only (see :mod:`mysim_jax.contact.law`).

This module imports nothing from :mod:`mysim_jax.config.scene` (which imports it); its models
share the base and field types of :mod:`mysim_jax.core.config_base`.
"""

from __future__ import annotations

import fnmatch
from typing import Annotated, Literal, NamedTuple

from pydantic import Field, model_validator

from mysim_jax.core.config_base import Finite, Name, NonNegFloat, PosFloat, StrictModel

GROUND = "ground"


class FrictionConfig(StrictModel):
    """Velocity-dependent Coulomb friction (paper Eq. collsion miu-v, made C¹).

    |μ| rises from 0 at zero slip to ``mu_static`` at ``v_static`` and settles to
    ``mu_dynamic`` from ``v_dynamic`` on (:func:`mysim_jax.contact.law.friction_coefficient`).
    """

    mu_static: NonNegFloat = 0.04
    mu_dynamic: NonNegFloat = 0.03
    v_static: PosFloat = 0.01       # m/s
    v_dynamic: PosFloat = 0.1       # m/s

    @model_validator(mode="after")
    def _ordered(self):
        if self.v_dynamic <= self.v_static:
            raise ValueError(
                f"friction.v_dynamic ({self.v_dynamic:g}) must be larger than friction.v_static "
                f"({self.v_static:g})"
            )
        return self


class SmoothingConfig(StrictModel):
    """Widths of the smooth contact model (``model: smooth``).

    ``depth`` [m]: softplus width of the penetration and of the max(0, ·) on the normal
    force (whose width is the elastic force at that depth, k·depthⁿ).
    ``velocity`` [m/s]: regularisation of the tangential slip speed, ``√(|v_t|² + v²)``.
    """

    depth: PosFloat = 1e-6
    velocity: PosFloat = 1e-4


class ContactGroupConfig(StrictModel):
    """A named set of collision shapes of ``radius`` [m]: spheres on the objects named by
    ``members``, or capsules on the rope and spring segments named by ``segments``
    (exactly one of the two; :class:`ContactConfig` checks it)."""

    name: Name
    members: Annotated[list[str], Field(min_length=1)] | None = None
    segments: Annotated[list[str], Field(min_length=1)] | None = None
    radius: PosFloat

    @property
    def is_segments(self) -> bool:
        """True for a group of capsules (``segments``), False for spheres (``members``)."""
        return self.segments is not None


class Segment(NamedTuple):
    """One spring of the scene, as contact sees it (names only, nothing resolved)."""

    name: str      # the scene's spring name: ``rope[j]`` or the spring's own name
    owner: str     # the rope or spring ``segments`` patterns match
    start: str     # reference of the end node at s = 0 (point, rope mass, body, body.marker, anchor)
    end: str       # reference of the end node at s = 1


def segment_table(ropes=(), springs=()) -> tuple[Segment, ...]:
    """Every spring of a scene in the order of ``Scene.spring_names``: each rope's
    ``n_masses + 1`` segments (masses ``rope_0 .. rope_{N-1}`` between its two ends), then
    the springs. ``ropes``/``springs``: objects with ``name``, ``start``, ``end`` (and
    ``n_masses`` for ropes), e.g. :class:`~mysim_jax.config.scene.RopeConfig`."""
    table = []
    for r in ropes:
        chain = [r.start] + [f"{r.name}_{j}" for j in range(r.n_masses)] + [r.end]
        table += [Segment(f"{r.name}[{j}]", r.name, chain[j], chain[j + 1]) for j in range(r.n_masses + 1)]
    table += [Segment(s.name, s.name, s.start, s.end) for s in springs]
    return tuple(table)


def segment_touches(segment: Segment, sphere: str, body_names) -> bool:
    """Whether ``sphere`` (a point or body name) sits on an end node of ``segment``: the end
    is that point, or that body (its centre or one of its markers ``body.marker``)."""
    for ref in (segment.start, segment.end):
        if ref == sphere or (sphere in body_names and ref.split(".", 1)[0] == sphere):
            return True
    return False


class BroadPhaseConfig(StrictModel):
    """Broad phase for sphere–capsule pairs (:mod:`mysim_jax.contact.broad_phase`): once
    per environment step, each sphere keeps its ``capsules`` nearest capsules; within the
    step only those pairs are evaluated. A capsule farther than ``margin`` [m] (surface
    gap) at the start of the step must not reach the sphere within the step: the margin
    must exceed the largest relative motion in one step (``sim.dt``). When more than
    ``capsules`` capsules are within the margin, the step evaluates all pairs."""

    capsules: Annotated[int, Field(ge=1, le=4096)] = 8
    margin: PosFloat = 0.05     # m


class ContactConfig(StrictModel):
    """Penalty contact between spheres (and with the ground plane z = 0).

    Normal force (paper Eq. compact_force, IMPACT form) with penetration δ ≥ 0:
    ``f = max(0, k·δⁿ + STEP(δ; 0, 0, p, c)·dδ/dt)`` along the line of centres.
    """

    model: Literal["sharp", "smooth"] = "sharp"
    stiffness: PosFloat                                  # k [N/m^n]
    exponent: Annotated[Finite, Field(ge=1, le=10)] = 1.0   # n
    damping: NonNegFloat = 0.0                           # c [N s/m]
    damping_depth: PosFloat                              # p [m]
    friction: FrictionConfig | None = None
    smoothing: SmoothingConfig = SmoothingConfig()
    groups: Annotated[list[ContactGroupConfig], Field(min_length=1)]
    pairs: Annotated[list[tuple[str, str]], Field(min_length=1)]
    broad_phase: BroadPhaseConfig | None = None          # None: every sphere–capsule pair, every sub-step

    @model_validator(mode="after")
    def _group_names(self):
        problems = []
        seen: set[str] = set()
        capsules: set[str] = set()
        for i, g in enumerate(self.groups):
            if g.name == GROUND:
                problems.append(f"contact.groups.{i}.name: '{GROUND}' is reserved for the ground plane")
            elif g.name in seen:
                problems.append(f"contact.groups.{i}.name: duplicate group name '{g.name}'")
            seen.add(g.name)
            if (g.members is None) == (g.segments is None):
                problems.append(
                    f"contact.groups.{i}: give exactly one of members (spheres on points and bodies) and "
                    f"segments (capsules on rope and spring segments); group '{g.name}' has "
                    + ("both" if g.members is not None else "neither"))
            elif g.is_segments:
                capsules.add(g.name)
        for i, (a, b) in enumerate(self.pairs):
            for k, ref in enumerate((a, b)):
                if ref != GROUND and ref not in seen:
                    problems.append(
                        f"contact.pairs.{i}.{k}: unknown contact group '{ref}' "
                        f"(groups: {', '.join(sorted(seen))}, or '{GROUND}')"
                    )
            if a == GROUND and b == GROUND:
                problems.append(f"contact.pairs.{i}: the ground cannot touch itself")
            elif a in capsules and b in capsules:
                problems.append(
                    f"contact.pairs.{i}: [{a}, {b}] pairs two segment groups; segment-segment (capsule-capsule) "
                    "contact is not modelled: pair the segments with a members group instead (e.g. spheres on "
                    "the rope masses)")
            elif GROUND in (a, b) and (a in capsules or b in capsules):
                problems.append(
                    f"contact.pairs.{i}: [{a}, {b}] puts segment group '{a if a in capsules else b}' on the "
                    "ground; segments do not touch the ground: ground contact of a net goes through spheres "
                    f"on its masses (a group with members such as ['r?_*'] paired with '{GROUND}')")
        if problems:
            raise ValueError("; ".join(problems))
        return self


def resolve_members(contact: ContactConfig, point_names: list[str], body_names: list[str],
                    anchor_names: set[str] | frozenset[str] = frozenset()):
    """Resolve every sphere group (``members``) to the objects it names.

    Returns ``(members, problems)``: ``members[group] = [(name, radius), ...]`` in scene
    order (points first, then bodies), and a list of error strings naming fields. Segment
    groups are left to :func:`resolve_segments`.
    """
    problems: list[str] = []
    objects = list(point_names) + list(body_names)
    radius_of: dict[str, tuple[float, int]] = {}
    members: dict[str, list[tuple[str, float]]] = {}
    for gi, group in enumerate(contact.groups):
        if group.is_segments:
            continue
        chosen: set[str] = set()
        for mi, pattern in enumerate(group.members):
            hits = [o for o in objects if fnmatch.fnmatchcase(o, pattern)]
            if not hits:
                why = ("is an anchor; spheres go on points and bodies" if pattern in anchor_names
                       else "matches no point mass, rope mass or body")
                problems.append(f"contact.groups.{gi}.members.{mi}: '{pattern}' {why}")
            chosen.update(hits)
        for name in chosen:
            if name in radius_of and radius_of[name][0] != group.radius:
                r, other = radius_of[name]
                problems.append(
                    f"contact.groups.{gi}.radius: '{name}' already has a sphere of radius {r:g} "
                    f"from contact.groups.{other} (one sphere per object)"
                )
            radius_of.setdefault(name, (group.radius, gi))
        members[group.name] = [(o, group.radius) for o in objects if o in chosen]
    return members, problems


def resolve_segments(contact: ContactConfig, segments: tuple[Segment, ...], object_names=()):
    """Resolve every segment group to the scene segments (``segment_table``) it names.

    Returns ``(capsules, problems)``: ``capsules[group] = [(Segment, radius), ...]`` in
    scene spring order, and error strings naming fields. ``object_names`` (points and
    bodies) only sharpen the message for a sphere's name put under ``segments``.
    """
    problems: list[str] = []
    owners = list(dict.fromkeys(seg.owner for seg in segments))
    radius_of: dict[str, tuple[float, int]] = {}
    capsules: dict[str, list[tuple[Segment, float]]] = {}
    for gi, group in enumerate(contact.groups):
        if not group.is_segments:
            continue
        chosen: set[str] = set()
        for mi, pattern in enumerate(group.segments):
            hits = [o for o in owners if fnmatch.fnmatchcase(o, pattern)]
            if not hits:
                why = "matches no rope or spring"
                if any(fnmatch.fnmatchcase(o, pattern) for o in object_names):
                    why += " (it names point masses or bodies: spheres on objects go under members)"
                problems.append(f"contact.groups.{gi}.segments.{mi}: '{pattern}' {why}")
            chosen.update(hits)
        picked = [seg for seg in segments if seg.owner in chosen]
        for seg in picked:
            if seg.name in radius_of and radius_of[seg.name][0] != group.radius:
                r, other = radius_of[seg.name]
                problems.append(
                    f"contact.groups.{gi}.radius: segment '{seg.name}' already has a capsule of radius {r:g} "
                    f"from contact.groups.{other} (one capsule per segment)"
                )
            radius_of.setdefault(seg.name, (group.radius, gi))
        capsules[group.name] = [(seg, group.radius) for seg in picked]
    return capsules, problems


def sphere_and_segment_groups(contact: ContactConfig, ga: str, gb: str):
    """``(sphere group, segment group)`` of the pair ``[ga, gb]`` in either order, or None
    if neither is a segment group."""
    kinds = {g.name: g.is_segments for g in contact.groups}
    if kinds.get(ga):
        return gb, ga
    if kinds.get(gb):
        return ga, gb
    return None


def capsule_pairs(contact: ContactConfig, ga: str, gb: str, members, capsules, body_names):
    """``[(sphere name, Segment), ...]`` that the pair ``[ga, gb]`` (one sphere group, one
    segment group) lists: every sphere against every capsule except its own segments."""
    spheres, segs = sphere_and_segment_groups(contact, ga, gb)
    bodies = set(body_names)
    return [(name, seg) for name, _ in members[spheres] for seg, _ in capsules[segs]
            if not segment_touches(seg, name, bodies)]


def pair_counts(contact: ContactConfig, members, capsules=None, body_names=()) -> list[int]:
    """Number of object pairs, (sphere, capsule) pairs or spheres on the ground that each
    entry of ``contact.pairs`` lists (``capsules`` from :func:`resolve_segments`)."""
    counts = []
    for ga, gb in contact.pairs:
        if GROUND in (ga, gb):
            counts.append(len(members[gb if ga == GROUND else ga]))
        elif sphere_and_segment_groups(contact, ga, gb) is not None:
            counts.append(len(capsule_pairs(contact, ga, gb, members, capsules or {}, body_names)))
        else:
            names_a = [n for n, _ in members[ga]]
            names_b = [n for n, _ in members[gb]]
            counts.append(len({(min(a, b), max(a, b)) for a in names_a for b in names_b if a != b}))
    return counts


def contact_problems(contact: ContactConfig, point_names: list[str], body_names: list[str],
                     anchor_names: set[str] | frozenset[str] = frozenset(), *, ropes=(), springs=()) -> list[str]:
    """Everything wrong with ``contact`` in a scene with these objects, as field-named strings:
    members or segments that match nothing, objects or segments with two radii, pairs that
    list no pair.

    ``ropes`` and ``springs`` (the scene's :class:`~mysim_jax.config.scene.RopeConfig` and
    :class:`~mysim_jax.config.scene.SpringConfig` entries) are what ``segments`` patterns match;
    their :func:`segment_table` is recorded on ``contact`` for
    :func:`~mysim_jax.contact.build.build_contact`.
    """
    table = segment_table(ropes, springs)
    members, problems = resolve_members(contact, point_names, body_names, anchor_names)
    capsules, segment_problems = resolve_segments(contact, table, list(point_names) + list(body_names))
    problems += segment_problems
    if problems:
        return problems
    counts = pair_counts(contact, members, capsules, body_names)
    sizes = {**{g: len(m) for g, m in members.items()}, **{g: len(c) for g, c in capsules.items()}}
    for i, ((ga, gb), n) in enumerate(zip(contact.pairs, counts)):
        if n == 0:
            what = "pair of objects (an object never touches itself"
            if sphere_and_segment_groups(contact, ga, gb) is not None:
                what = "(sphere, segment) pair (a sphere never touches the segments it is an end of"
            problems.append(
                f"contact.pairs.{i}: [{ga}, {gb}] lists no {what}; "
                f"group '{ga}' has {sizes.get(ga, 0)} member(s)"
                + ("" if ga == gb else f", group '{gb}' {sizes.get(gb, 0)}") + ")")
    return problems
