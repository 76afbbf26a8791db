"""Host-side assembly of the contact structure (NumPy only, nothing traced).

:func:`build_contact` turns the validated ``contact:`` block into a static
:class:`~mysim_jax.contact.types.ContactScene`, traced
:class:`~mysim_jax.contact.types.ContactParams`, and the explicit stability limit of the
stiffest contact for fixed-step integrators (:func:`contact_stable_step`).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from mysim_jax.contact.config import GROUND, ContactConfig, resolve_members
from mysim_jax.contact.types import ContactParams, ContactScene
from mysim_jax.dynamics.stability import spring_stable_steps


def build_contact(contact: ContactConfig, point_names, body_names, dtype):
    """``(ContactScene, ContactParams)`` of a scene; names resolved by the config check."""
    members, problems = resolve_members(contact, list(point_names), list(body_names))
    if problems:       # the config validator has already reported these; defensive only
        raise ValueError("; ".join(problems))
    radius_of: dict[str, float] = {}
    used_pairs: set[tuple[str, str]] = set()
    used_ground: set[str] = set()
    for ga, gb in contact.pairs:
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

    point_index = {n: i for i, n in enumerate(point_names)}
    body_index = {n: i for i, n in enumerate(body_names)}
    on_points = [n for n in point_names if n in radius_of]
    on_bodies = [n for n in body_names if n in radius_of]
    sphere_names = on_points + on_bodies
    sphere = {n: i for i, n in enumerate(sphere_names)}
    pairs = sorted((min(sphere[x], sphere[y]), max(sphere[x], sphere[y])) for x, y in used_pairs)
    cscene = ContactScene(
        sphere_names=tuple(sphere_names),
        sphere_point=tuple(point_index[n] for n in on_points),
        sphere_body=tuple(body_index[n] for n in on_bodies),
        pair_a=tuple(p[0] for p in pairs),
        pair_b=tuple(p[1] for p in pairs),
        ground_sphere=tuple(sorted(sphere[n] for n in used_ground)),
        model=contact.model,
        friction=contact.friction is not None,
    )
    fr = contact.friction

    def scalar(x):
        return jnp.asarray(x, dtype=dtype)

    cparams = ContactParams(
        radius=jnp.asarray(np.asarray([radius_of[n] for n in sphere_names], float).reshape(-1), dtype=dtype),
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
    )
    return cscene, cparams


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
    """
    if cscene.n_pairs == 0 and cscene.n_ground == 0:
        return math.inf, ""
    k_lin = contact.exponent * contact.stiffness * contact.damping_depth ** (contact.exponent - 1.0)
    inv_mass = np.concatenate([1.0 / np.asarray(point_mass, float)[list(cscene.sphere_point)],
                               1.0 / np.asarray(body_mass, float)[list(cscene.sphere_body)]])
    ends_a = list(cscene.pair_a) + list(cscene.ground_sphere)
    inv_a = [inv_mass[i] for i in ends_a]
    inv_b = [inv_mass[i] for i in cscene.pair_b] + [0.0] * cscene.n_ground
    names = cscene.pair_names() + [f"{cscene.sphere_names[i]}|ground" for i in cscene.ground_sphere]
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
