"""Host-side assembly of the contact structure (NumPy only, nothing traced).

:func:`build_contact` turns the validated ``contact:`` block into a static
:class:`~mysim_jax.core.contact_types.ContactScene`, traced
:class:`~mysim_jax.core.contact_types.ContactParams`, and the explicit stability limit of the
stiffest contact for fixed-step integrators (:func:`contact_stable_step`).

Capsules are listed by the scene's spring names (``rope[j]``); their end nodes are looked
up in the :class:`~mysim_jax.core.types.Scene`'s spring tables when the force stage is traced
(:func:`mysim_jax.contact.forces.capsule_nodes`), so node numbering stays the scene
builder's business.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from mysim_jax.contact.config import (GROUND, ContactConfig, capsule_pairs, resolve_members, resolve_segments,
                                      sphere_and_segment_groups)
from mysim_jax.core.contact_types import BroadPhaseScene, ContactParams, ContactScene
from mysim_jax.dynamics.stability import spring_stable_steps


def _used_pairs(contact: ContactConfig, members, capsules, body_names):
    """Which spheres touch which (by name) after the pair list: ``(radius of every sphere
    in a pair, sphere pairs, spheres on the ground, (sphere, capsule) pairs, capsule of
    every spring in a pair as (Segment, radius))``."""
    radius_of: dict[str, float] = {}
    used_pairs: set[tuple[str, str]] = set()
    used_ground: set[str] = set()
    used_capsule_pairs: set[tuple[str, str]] = set()     # (sphere name, spring name)
    capsule_of: dict[str, tuple] = {}                     # spring name -> (Segment, radius)
    for ga, gb in contact.pairs:
        groups = sphere_and_segment_groups(contact, ga, gb)
        if groups is not None:
            sphere_radius = dict(members[groups[0]])
            capsule_radius = {seg.name: (seg, r) for seg, r in capsules[groups[1]]}
            for name, seg in capsule_pairs(contact, ga, gb, members, capsules, body_names):
                radius_of[name] = sphere_radius[name]
                capsule_of[seg.name] = capsule_radius[seg.name]
                used_capsule_pairs.add((name, seg.name))
            continue
        if GROUND in (ga, gb):
            group = gb if ga == GROUND else ga
            for name, r in members[group]:
                used_ground.add(name)
                radius_of[name] = r
            continue
        for name_a, ra in members[ga]:
            for name_b, rb in members[gb]:
                if name_a == name_b:
                    continue
                radius_of[name_a], radius_of[name_b] = ra, rb
                used_pairs.add((name_a, name_b) if name_a < name_b else (name_b, name_a))
    return radius_of, used_pairs, used_ground, used_capsule_pairs, capsule_of


def _contact_params(contact: ContactConfig, radii, capsule_radii, dtype) -> ContactParams:
    """The contact law's constants as arrays of ``dtype``."""
    fr = contact.friction

    def scalar(x):
        return jnp.asarray(x, dtype=dtype)

    return ContactParams(
        radius=jnp.asarray(np.asarray(radii, float).reshape(-1), dtype=dtype),
        stiffness=scalar(contact.stiffness),
        exponent=scalar(contact.exponent),
        damping=scalar(contact.damping),
        damping_depth=scalar(contact.damping_depth),
        mu_static=scalar(fr.mu_static if fr else 0.0),
        mu_dynamic=scalar(fr.mu_dynamic if fr else 0.0),
        v_static=scalar(fr.v_static if fr else 1.0),
        v_dynamic=scalar(fr.v_dynamic if fr else 2.0),
        smooth_depth=scalar(contact.smoothing.depth),
        smooth_velocity=scalar(contact.smoothing.velocity),
        capsule_radius=jnp.asarray(np.asarray(capsule_radii, float), dtype=dtype) if capsule_radii else None,
    )


def build_contact(contact: ContactConfig, point_names, body_names, dtype, segments=None):
    """``(ContactScene, ContactParams)`` of a scene; names resolved by the config check.

    ``segments``: the scene's springs as :func:`~mysim_jax.contact.config.segment_table`
    lists them; by default the table recorded on ``contact`` when the scene config was
    validated (:func:`~mysim_jax.contact.config.contact_problems`). Only segment groups
    need it.
    """
    members, problems = resolve_members(contact, list(point_names), list(body_names))
    capsule_groups = [g for g in contact.groups if g.is_segments]
    capsules: dict = {}
    if capsule_groups:
        if segments is None:
            raise ValueError("contact.groups: segment groups need the scene's ropes and springs: pass "
                             "segments=segment_table(ropes, springs)")
        capsules, more = resolve_segments(contact, tuple(segments), list(point_names) + list(body_names))
        problems += more
    if problems:       # the config validator has already reported these; defensive only
        raise ValueError("; ".join(problems))
    used = _used_pairs(contact, members, capsules, body_names)
    radius_of, used_pairs, used_ground, used_capsule_pairs, capsule_of = used

    point_index = {n: i for i, n in enumerate(point_names)}
    body_index = {n: i for i, n in enumerate(body_names)}
    on_points = [n for n in point_names if n in radius_of]
    on_bodies = [n for n in body_names if n in radius_of]
    sphere_names = on_points + on_bodies
    sphere = {n: i for i, n in enumerate(sphere_names)}
    pairs = sorted((min(sphere[x], sphere[y]), max(sphere[x], sphere[y])) for x, y in used_pairs)
    # capsules in scene spring order, then (sphere, capsule) pairs sorted by sphere
    order = {seg.name: i for i, seg in enumerate(segments or ())}
    capsule_names = sorted(capsule_of, key=order.__getitem__)
    capsule = {n: i for i, n in enumerate(capsule_names)}
    cpairs = sorted((sphere[x], capsule[c]) for x, c in used_capsule_pairs)

    def end_object(ref: str) -> int:
        """Index into points then bodies of the mass an end node moves, −1 for an anchor."""
        if ref in point_index:
            return point_index[ref]
        body = ref.split(".", 1)[0]
        return len(point_index) + body_index[body] if body in body_index else -1

    ends = [capsule_of[n][0] for n in capsule_names]
    cscene = ContactScene(
        sphere_names=tuple(sphere_names),
        sphere_point=tuple(point_index[n] for n in on_points),
        sphere_body=tuple(body_index[n] for n in on_bodies),
        pair_a=tuple(p[0] for p in pairs),
        pair_b=tuple(p[1] for p in pairs),
        ground_sphere=tuple(sorted(sphere[n] for n in used_ground)),
        capsule_names=tuple(capsule_names),
        capsule_end_names=tuple((seg.start, seg.end) for seg in ends),
        capsule_end_object_a=tuple(end_object(seg.start) for seg in ends),
        capsule_end_object_b=tuple(end_object(seg.end) for seg in ends),
        capsule_pair_sphere=tuple(p[0] for p in cpairs),
        capsule_pair_capsule=tuple(p[1] for p in cpairs),
        model=contact.model,
        friction=contact.friction is not None,
        broad_phase=(None if contact.broad_phase is None else
                     BroadPhaseScene(capsules=contact.broad_phase.capsules, margin=float(contact.broad_phase.margin))),
    )
    return cscene, _contact_params(contact, [radius_of[n] for n in sphere_names],
                                   [capsule_of[n][1] for n in capsule_names], dtype)


def contact_stable_step(integrator: str, contact: ContactConfig, cscene: ContactScene,
                        point_mass, body_mass) -> tuple[float, str]:
    """Explicit stability limit of the stiffest contact, and a description of it.

    Each pair in contact is a spring-damper along the line of centres with the
    linearised stiffness ``n·k·pⁿ⁻¹`` (k itself for n = 1; for n > 1 the stiffness at the
    damping depth p, below which the paper's contacts stay) and the full damping ``c``,
    joining the two masses (the ground: infinite mass). The normal force acts through
    the centres of mass, so rotational inertia does not enter. Friction is not counted:
    its force is bounded by μ·f, so an explicit step that over-shoots zero slip chatters
    at an amplitude of order ``h·μ·f/m`` instead of diverging.

    A sphere against a capsule: the segment point at parameter s moves like a mass of
    inverse ``(1 − s)²/m_a + s²/m_b`` (the force splits (1 − s), s onto the end nodes, and
    the point moves with the same weights). That is convex in s, so its largest value over
    the segment is at an end, ``max(1/m_a, 1/m_b)``: this bound is used, which is exact for
    a sphere at either end and safe in between. An end on a body (its centre or a marker)
    counts the body's mass — a stand-in that ignores the body's rotation (a marker away from
    the centre of mass moves more easily); an anchor end is infinitely heavy (1/m = 0).
    """
    if cscene.n_pairs == 0 and cscene.n_ground == 0 and cscene.n_capsule_pairs == 0:
        return math.inf, ""
    k_lin = contact.exponent * contact.stiffness * contact.damping_depth ** (contact.exponent - 1.0)
    point_inv = 1.0 / np.asarray(point_mass, float).reshape(-1)
    body_inv = 1.0 / np.asarray(body_mass, float).reshape(-1)
    inv_mass = np.concatenate([point_inv[list(cscene.sphere_point)], body_inv[list(cscene.sphere_body)]])
    object_inv = np.concatenate([point_inv, body_inv, [0.0]])      # index −1: an anchor
    capsule_inv = [max(object_inv[a], object_inv[b])
                   for a, b in zip(cscene.capsule_end_object_a, cscene.capsule_end_object_b)]
    ends_a = list(cscene.pair_a) + list(cscene.ground_sphere) + list(cscene.capsule_pair_sphere)
    inv_a = [inv_mass[i] for i in ends_a]
    inv_b = ([inv_mass[i] for i in cscene.pair_b] + [0.0] * cscene.n_ground
             + [capsule_inv[c] for c in cscene.capsule_pair_capsule])
    names = (cscene.pair_names() + [f"{cscene.sphere_names[i]}|ground" for i in cscene.ground_sphere]
             + cscene.capsule_pair_names())
    # equal (k, c, 1/m) give equal limits: evaluate each distinct mass combination once
    keys = sorted(set(zip(inv_a, inv_b)))
    limits = spring_stable_steps(integrator, [k_lin] * len(keys), [contact.damping] * len(keys),
                                 [k[0] for k in keys], [k[1] for k in keys])
    by_key = dict(zip(keys, limits))
    per_contact = np.array([by_key[(x, y)] for x, y in zip(inv_a, inv_b)])
    worst = int(np.argmin(per_contact))
    return float(per_contact[worst]), (
        f"contact '{names[worst]}' (k = {k_lin:.4g} N/m, c = {contact.damping:.4g} N s/m)"
    )
