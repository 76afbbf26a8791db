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

``friction`` is left out (or ``null``) for frictionless contact. ``smoothing`` is used by
``model: smooth`` only (see :mod:`mysim_jax.contact.law`).

This module imports nothing from :mod:`mysim_jax.config` (which imports it); its models
share the base and field types of :mod:`mysim_jax.config_base`.
"""

from __future__ import annotations

import fnmatch
from typing import Annotated, Literal

from pydantic import Field, model_validator

from mysim_jax.config_base import Finite, Name, NonNegFloat, PosFloat, StrictModel

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
    """A named set of collision objects, each carrying a sphere of ``radius`` [m]."""

    name: Name
    members: Annotated[list[str], Field(min_length=1)]
    radius: PosFloat


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

    @model_validator(mode="after")
    def _group_names(self):
        problems = []
        seen: set[str] = set()
        for i, g in enumerate(self.groups):
            if g.name == GROUND:
                problems.append(f"contact.groups.{i}.name: '{GROUND}' is reserved for the ground plane")
            elif g.name in seen:
                problems.append(f"contact.groups.{i}.name: duplicate group name '{g.name}'")
            seen.add(g.name)
        for i, (a, b) in enumerate(self.pairs):
            for k, ref in enumerate((a, b)):
                if ref != GROUND and ref not in seen:
                    problems.append(
                        f"contact.pairs.{i}.{k}: unknown contact group '{ref}' "
                        f"(groups: {', '.join(sorted(seen))}, or '{GROUND}')"
                    )
            if a == GROUND and b == GROUND:
                problems.append(f"contact.pairs.{i}: the ground cannot touch itself")
        if problems:
            raise ValueError("; ".join(problems))
        return self


def resolve_members(contact: ContactConfig, point_names: list[str], body_names: list[str],
                    anchor_names: set[str] | frozenset[str] = frozenset()):
    """Resolve every group to the objects it names.

    Returns ``(members, problems)``: ``members[group] = [(name, radius), ...]`` in scene
    order (points first, then bodies), and a list of error strings naming fields.
    """
    problems: list[str] = []
    objects = list(point_names) + list(body_names)
    radius_of: dict[str, tuple[float, int]] = {}
    members: dict[str, list[tuple[str, float]]] = {}
    for gi, group in enumerate(contact.groups):
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


def pair_counts(contact: ContactConfig, members) -> list[int]:
    """Number of object pairs (or spheres on the ground) each entry of ``contact.pairs`` lists."""
    counts = []
    for ga, gb in contact.pairs:
        if GROUND in (ga, gb):
            counts.append(len(members[gb if ga == GROUND else ga]))
        else:
            names_a = [n for n, _ in members[ga]]
            names_b = [n for n, _ in members[gb]]
            counts.append(len({(min(a, b), max(a, b)) for a in names_a for b in names_b if a != b}))
    return counts


def contact_problems(contact: ContactConfig, point_names: list[str], body_names: list[str],
                     anchor_names: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """Everything wrong with ``contact`` in a scene with these objects, as field-named strings:
    members that match nothing, objects with two radii, pairs that list no pair."""
    members, problems = resolve_members(contact, point_names, body_names, anchor_names)
    if problems:
        return problems
    for i, ((ga, gb), n) in enumerate(zip(contact.pairs, pair_counts(contact, members))):
        if n == 0:
            problems.append(
                f"contact.pairs.{i}: [{ga}, {gb}] lists no pair of objects (an object never touches itself; "
                f"group '{ga}' has {len(members.get(ga, []))} member(s)"
                + ("" if ga == gb else f", group '{gb}' {len(members.get(gb, []))}") + ")")
    return problems
