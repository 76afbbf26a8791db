"""Mechanical energy of one state, for energy checks of contact scenes.

``E = kinetic (points, bodies: ½mv² + ½ωᵀJω) + gravity (−m g·x)
      + springs (½k(s − s̄)², tension-only springs only while taut)
      + contacts (k·δⁿ⁺¹/(n+1) for every overlapping pair, ground contact and
                  sphere–capsule contact)``

Dampers, the clipped part of the contact force and friction only take energy out, so for
a scene without actuators or applied loads ``E(t) ≤ E(0)`` holds for the exact solution:
"never above the initial energy plus the work gravity did". Applied loads, joints and
actuators are not counted (their work is not a potential here). The contact term is the
sharp law's potential; for ``model: smooth`` it is an approximation within the
smoothing width.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mysim_jax.core import vecmath
from mysim_jax.contact.forces import capsule_geometry, pair_penetration, sphere_kinematics
from mysim_jax.dynamics.forces import spring_lengths
from mysim_jax.dynamics.markers import node_states
from mysim_jax.core.types import Params, PhysState, Scene


def _contact_potential(depth, cp):
    pen = jnp.maximum(depth, 0.0)
    return jnp.sum(jnp.where(depth > 0.0, cp.stiffness * pen ** (cp.exponent + 1.0) / (cp.exponent + 1.0), 0.0))


def mechanical_energy(scene: Scene, params: Params, phys: PhysState):
    """Total mechanical energy [J] of one environment (a scalar)."""
    energy = 0.5 * jnp.sum(params.point_mass * vecmath.dot(phys.point_vel, phys.point_vel))
    if scene.has_gravity:
        energy = energy - jnp.sum(params.point_mass * (phys.point_pos @ params.gravity))
    if scene.n_bodies:
        energy = energy + 0.5 * jnp.sum(params.body_mass * vecmath.dot(phys.body_vel, phys.body_vel))
        j_omega = jnp.einsum("nij,nj->ni", params.body_inertia, phys.body_angvel)
        energy = energy + 0.5 * jnp.sum(vecmath.dot(phys.body_angvel, j_omega))
        if scene.has_gravity:
            energy = energy - jnp.sum(params.body_mass * (phys.body_pos @ params.gravity))
    if scene.n_springs:
        node_pos, _ = node_states(scene, params, phys)
        stretch = spring_lengths(scene, node_pos) - params.spring_rest_length
        taut = np.asarray(scene.spring_tension_only, bool)
        stretch = jnp.where(jnp.asarray(taut) & (stretch < 0.0), 0.0, stretch)
        energy = energy + 0.5 * jnp.sum(params.spring_stiffness * stretch * stretch)
    if scene.contact is not None:
        cs, cp = scene.contact, params.contact
        pos, _, _ = sphere_kinematics(scene, phys)
        if cs.n_pairs:
            energy = energy + _contact_potential(pair_penetration(scene, params, pos), cp)
        if cs.n_ground:
            g = np.asarray(cs.ground_sphere, np.int32)
            energy = energy + _contact_potential(cp.radius[g] - pos[g, 2], cp)
        if cs.n_capsule_pairs:
            node_pos, _ = node_states(scene, params, phys)
            energy = energy + _contact_potential(capsule_geometry(scene, params, pos, node_pos)[4], cp)
    return energy
