"""The ``contact_forces`` stage: sphere–sphere and sphere–ground penalty contact.

For a pair (a, b) with centres ``x_a``, ``x_b`` and radii ``r_a``, ``r_b``:

* normal ``n = (x_b − x_a)/|x_b − x_a|`` (world +z when the centres coincide exactly, so
  two spheres started at the same place are pushed apart instead of staying merged with
  no force);
* penetration ``δ = r_a + r_b − |x_b − x_a|``, rate ``dδ/dt = −(v_b − v_a)·n``;
* normal force ``f(δ, dδ/dt)`` from :mod:`mysim_jax.contact.law` (sharp or smooth), on b
  along +n and on a along −n;
* contact point in the middle of the overlap, at lever arms ``(r_a − δ/2)·n`` from a and
  ``−(r_b − δ/2)·n`` from b; friction opposes the tangential slip of b's contact point
  relative to a's, including ``ω × lever`` of rigid bodies (ω rotated to the world frame),
  and turns bodies by ``lever × F``.

The ground is the plane z = 0 with normal +z (penetration ``r − z``).

Forces land on point masses as node forces and on bodies as force at the centre of mass
plus body-frame torque (:class:`~mysim_jax.dynamics.forces.Loads`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mysim_jax import vecmath
from mysim_jax.contact import law
from mysim_jax.dynamics.forces import Loads
from mysim_jax.dynamics.markers import scatter_rows
from mysim_jax.dynamics.quaternion import quat_rotate, quat_rotate_inv
from mysim_jax.types import Params, PhysState, Scene


def _normal_force(scene: Scene, cp, depth, depth_rate):
    return law.CONTACT_LAWS[scene.contact.model].normal_force(depth, depth_rate, cp)


def _friction(scene: Scene, cp, normal_force, slip):
    """Friction force ``(k, 3)`` on the sphere whose contact point slips at ``slip``."""
    speed_sq = law.CONTACT_LAWS[scene.contact.model].slip_speed_sq(vecmath.dot(slip, slip), cp)
    g = law.friction_per_speed(speed_sq, cp.mu_static, cp.mu_dynamic, cp.v_static, cp.v_dynamic)
    return -(normal_force * g)[:, None] * slip


def sphere_kinematics(scene: Scene, phys: PhysState):
    """Centres, velocities and world angular velocities ``(n_spheres, 3)`` of all spheres
    (angular velocity zero for point masses)."""
    cs = scene.contact
    pts = np.asarray(cs.sphere_point, dtype=np.int32)
    bods = np.asarray(cs.sphere_body, dtype=np.int32)
    pos = jnp.concatenate([phys.point_pos[pts], phys.body_pos[bods]], axis=0)
    vel = jnp.concatenate([phys.point_vel[pts], phys.body_vel[bods]], axis=0)
    omega = jnp.concatenate([jnp.zeros_like(phys.point_vel[pts]),
                             quat_rotate(phys.body_quat[bods], phys.body_angvel[bods])], axis=0)
    return pos, vel, omega


def pair_penetration(scene: Scene, params: Params, sphere_pos):
    """Penetration depth ``(n_pairs,)`` of every listed pair (negative: the gap)."""
    cs = scene.contact
    a = np.asarray(cs.pair_a, dtype=np.int32)
    b = np.asarray(cs.pair_b, dtype=np.int32)
    r = params.contact.radius
    return r[a] + r[b] - vecmath.safe_norm(sphere_pos[b] - sphere_pos[a])


def _pair_forces(scene, cp, pos, vel, omega):
    """Force on b (world) ``(n_pairs, 3)`` and the torques on a and b (world)."""
    cs = scene.contact
    a = np.asarray(cs.pair_a, dtype=np.int32)
    b = np.asarray(cs.pair_b, dtype=np.int32)
    d = pos[b] - pos[a]
    dist, n = vecmath.safe_unit(d)
    up = jnp.zeros_like(n).at[:, 2].set(1.0)
    n = jnp.where((dist > 0.0)[:, None], n, up)
    depth = cp.radius[a] + cp.radius[b] - dist
    dv = vel[b] - vel[a]
    fn = _normal_force(scene, cp, depth, -vecmath.dot(dv, n))
    force_b = fn[:, None] * n
    torque_a = torque_b = None
    if cs.friction:
        lever_a = (cp.radius[a] - 0.5 * depth)[:, None] * n
        lever_b = -(cp.radius[b] - 0.5 * depth)[:, None] * n
        v_rel = dv + vecmath.cross(omega[b], lever_b) - vecmath.cross(omega[a], lever_a)
        slip = v_rel - vecmath.dot(v_rel, n)[:, None] * n
        friction_b = _friction(scene, cp, fn, slip)
        force_b = force_b + friction_b
        # the normal part is parallel to the levers: only friction turns the bodies
        torque_b = vecmath.cross(lever_b, friction_b)
        torque_a = vecmath.cross(lever_a, -friction_b)
    return force_b, torque_a, torque_b


def _ground_forces(scene, cp, pos, vel, omega):
    """Force ``(n_ground, 3)`` and torque (world) on each sphere touching the ground."""
    cs = scene.contact
    g = np.asarray(cs.ground_sphere, dtype=np.int32)
    radius = cp.radius[g]
    depth = radius - pos[g, 2]
    fn = _normal_force(scene, cp, depth, -vel[g, 2])
    up = jnp.zeros_like(pos[g]).at[:, 2].set(1.0)
    force = fn[:, None] * up
    torque = None
    if cs.friction:
        lever = -(radius - 0.5 * depth)[:, None] * up
        v_contact = vel[g] + vecmath.cross(omega[g], lever)
        slip = v_contact.at[:, 2].set(0.0)
        friction = _friction(scene, cp, fn, slip)
        force = force + friction
        torque = vecmath.cross(lever, friction)
    return force, torque


def contact_forces(scene: Scene, params: Params, phys: PhysState, nodes=None, inputs=None) -> Loads:
    """Force stage ``fn(scene, params, phys, nodes, inputs) -> Loads`` of all contacts."""
    cs = scene.contact
    cp = params.contact
    pos, vel, omega = sphere_kinematics(scene, phys)
    n_spheres = cs.n_spheres
    rows, index = [], []
    with_torque = cs.friction and len(cs.sphere_body) > 0
    if cs.n_pairs:
        force_b, torque_a, torque_b = _pair_forces(scene, cp, pos, vel, omega)
        if with_torque:
            rows += [jnp.concatenate([-force_b, torque_a], -1), jnp.concatenate([force_b, torque_b], -1)]
        else:
            rows += [-force_b, force_b]
        index += [cs.pair_a, cs.pair_b]
    if cs.n_ground:
        force, torque = _ground_forces(scene, cp, pos, vel, omega)
        rows.append(jnp.concatenate([force, torque], -1) if with_torque else force)
        index.append(cs.ground_sphere)
    # one scatter of all contributions onto the sphere table
    per_sphere = scatter_rows(jnp.concatenate(rows, 0), np.concatenate([np.asarray(i, np.int32) for i in index]),
                              n_spheres, scene.accumulate)
    n_pt = len(cs.sphere_point)
    dtype = pos.dtype
    node_force = jnp.zeros((scene.n_nodes, 3), dtype=dtype)
    if n_pt:
        node_force = node_force.at[np.asarray(cs.sphere_point, np.int32)].add(per_sphere[:n_pt, :3])
    body_force = jnp.zeros((scene.n_bodies, 3), dtype=dtype)
    body_torque = jnp.zeros((scene.n_bodies, 3), dtype=dtype)
    if len(cs.sphere_body):
        bods = np.asarray(cs.sphere_body, np.int32)
        body_force = body_force.at[bods].add(per_sphere[n_pt:, :3])
        if with_torque:
            body_torque = body_torque.at[bods].add(quat_rotate_inv(phys.body_quat[bods], per_sphere[n_pt:, 3:]))
    return Loads(node_force=node_force, body_force=body_force, body_torque=body_torque)
