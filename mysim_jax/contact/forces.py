"""The ``contact_forces`` stage: sphere–sphere, sphere–ground and sphere–capsule penalty contact.

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

Sphere against capsule
----------------------
A capsule is the set of points within ``r_c`` of a segment between two nodes ``a`` and
``b`` (point masses, body markers or anchors: the ``(node_pos, node_vel)`` table of the
force pipeline). For a sphere of centre ``x`` and radius ``r``:

* closest segment point ``p = a + s·(b − a)`` with
  ``s = clip((x − a)·(b − a)/|b − a|², 0, 1)``; a segment shorter than
  :data:`MIN_SEGMENT_LENGTH` counts as the point ``a`` (``s = 0``, finite gradients);
* normal ``n = (x − p)/|x − p|`` (world +z when x lies on the axis), penetration
  ``δ = r + r_c − |x − p|``; the segment point moves at ``v_p = (1 − s)·v_a + s·v_b`` and
  ``dδ/dt = −(v_x − v_p)·n`` (exact: the motion of s itself is perpendicular to n);
* the same normal and friction laws as sphere pairs; friction opposes the tangential slip
  of the sphere's contact point (at lever ``−(r − δ/2)·n``, with ω × lever for a body
  sphere) relative to the segment point ``p``;
* the force ``F`` on the sphere acts through its centre (plus the friction torque), and
  ``−F`` is shared by the end nodes as ``−(1 − s)·F`` on ``a`` and ``−s·F`` on ``b``:
  node forces, so points take them directly, markers pass them to their bodies
  (``distribute_node_forces``) and anchors drop them.

Forces balance exactly. Without friction the moments about the sphere centre balance too
(``p − x`` is parallel to ``F``); friction acts on the segment at ``p`` rather than at the
capsule's surface, so its moment arm ``r_c`` about the axis is not transmitted (a segment
between two nodes cannot take a torque about itself). The normal force is the gradient of
``k·δⁿ⁺¹/(n+1)`` (s is a minimiser, so ∂δ/∂s = 0), so sharp contact without damping
conserves energy (:mod:`mysim_jax.contact.energy` counts it).

Forces land on point masses as node forces and on bodies as force at the centre of mass
plus body-frame torque (:class:`~mysim_jax.dynamics.forces.Loads`).

With ``contact.broad_phase`` the stage evaluates the sphere–capsule pairs the broad phase
chose at the start of the step (:mod:`mysim_jax.contact.broad_phase`) instead of all of
them; the forces are the same as long as the choice foresaw every contact.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import vecmath
from mysim_jax.contact import law
from mysim_jax.dynamics.forces import Loads
from mysim_jax.dynamics.markers import node_states, scatter_rows
from mysim_jax.dynamics.quaternion import quat_rotate, quat_rotate_inv
from mysim_jax.core.types import Params, PhysState, Scene

MIN_SEGMENT_LENGTH = 1e-9
"""[m] A capsule's segment shorter than this is treated as its first end point."""


def _normal_force(scene: Scene, cp, depth, depth_rate):
    return law.CONTACT_LAWS[scene.contact.model].normal_force(depth, depth_rate, cp)


def _friction(scene: Scene, cp, normal_force, slip):
    """Friction force on b, under its own named scope (traced only when the scene has friction)."""
    with jax.named_scope("friction"):
        return _friction_law(scene, cp, normal_force, slip)


def _friction_law(scene: Scene, cp, normal_force, slip):
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


def closest_point_on_segment(x, a, b):
    """Parameter ``s`` ``(k,)`` in [0, 1] and point ``a + s·(b − a)`` ``(k, 3)`` of each
    segment closest to ``x``; ``s = 0`` on a segment shorter than :data:`MIN_SEGMENT_LENGTH`
    (no NaN in values or gradients at zero length)."""
    ab = b - a
    length_sq = vecmath.dot(ab, ab)
    long_enough = length_sq > MIN_SEGMENT_LENGTH * MIN_SEGMENT_LENGTH
    t = vecmath.dot(x - a, ab) / jnp.where(long_enough, length_sq, 1.0)
    s = jnp.where(long_enough, jnp.clip(t, 0.0, 1.0), 0.0)
    return s, a + s[:, None] * ab


def _node_name(scene: Scene, node: int) -> str:
    if node < scene.n_points:
        return scene.point_names[node]
    if node < scene.n_points + scene.n_markers:
        return scene.marker_names[node - scene.n_points]
    return scene.anchor_names[node - scene.n_points - scene.n_markers]


def capsule_nodes(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """End node indices ``(n_capsules,)`` at s = 0 and s = 1 of every capsule, looked up in
    the scene's spring tables by name (static, when the stage is traced).

    Raises ``ValueError`` if a capsule's spring is missing or joins other nodes than the
    contact scene was built for (a contact scene built from another scene's springs).
    """
    cs = scene.contact
    spring = {name: k for k, name in enumerate(scene.spring_names)}
    node_a, node_b = [], []
    for name, ends in zip(cs.capsule_names, cs.capsule_end_names):
        k = spring.get(name)
        if k is None or (_node_name(scene, scene.spring_node_a[k]), _node_name(scene, scene.spring_node_b[k])) != ends:
            raise ValueError(f"contact capsule '{name}' ({ends[0]} - {ends[1]}) is not a spring of the "
                             f"scene: the contact scene was built for other springs")
        node_a.append(scene.spring_node_a[k])
        node_b.append(scene.spring_node_b[k])
    return np.asarray(node_a, np.int32), np.asarray(node_b, np.int32)


def capsule_pair_indices(scene: Scene, pairs=None):
    """``(sphere, capsule, node_a, node_b)`` index arrays ``(k,)`` of the sphere–capsule
    pairs ``pairs`` (indices into the scene's pair table, traced or static; None: all,
    static)."""
    cs = scene.contact
    sph = np.asarray(cs.capsule_pair_sphere, dtype=np.int32)
    cap = np.asarray(cs.capsule_pair_capsule, dtype=np.int32)
    node_a, node_b = capsule_nodes(scene)
    if pairs is None:
        return sph, cap, node_a[cap], node_b[cap]
    return (jnp.asarray(sph)[pairs], jnp.asarray(cap)[pairs], jnp.asarray(node_a[cap])[pairs],
            jnp.asarray(node_b[cap])[pairs])


def capsule_geometry(scene: Scene, params: Params, sphere_pos, node_pos, pairs=None):
    """``(s, p, distance, n, penetration)`` of the sphere–capsule pairs ``pairs`` (None:
    all): segment parameter ``(k,)``, closest segment point ``(k, 3)``, its distance to
    the sphere centre ``(k,)``, unit normal from the segment to the sphere ``(k, 3)`` (+z
    on the axis) and penetration ``(k,)`` (negative: the gap)."""
    cp = params.contact
    sph, cap, end_a, end_b = capsule_pair_indices(scene, pairs)
    x = sphere_pos[sph]
    s, p = closest_point_on_segment(x, node_pos[end_a], node_pos[end_b])
    dist, n = vecmath.safe_unit(x - p)
    up = jnp.zeros_like(n).at[:, 2].set(1.0)
    n = jnp.where((dist > 0.0)[:, None], n, up)
    depth = cp.radius[sph] + cp.capsule_radius[cap] - dist
    return s, p, dist, n, depth


def _capsule_forces(scene, params, pos, vel, omega, node_pos, node_vel, pairs=None):
    """Force on the sphere (world) ``(k, 3)``, its torque (world, None without friction),
    and the segment parameter ``s`` ``(k,)`` of the sphere–capsule pairs ``pairs`` (None:
    all)."""
    cs, cp = scene.contact, params.contact
    sph, _, end_a, end_b = capsule_pair_indices(scene, pairs)
    s, _, _, n, depth = capsule_geometry(scene, params, pos, node_pos, pairs)
    v_seg = (1.0 - s)[:, None] * node_vel[end_a] + s[:, None] * node_vel[end_b]
    dv = vel[sph] - v_seg
    fn = _normal_force(scene, cp, depth, -vecmath.dot(dv, n))
    force = fn[:, None] * n
    torque = None
    if cs.friction:
        lever = -(cp.radius[sph] - 0.5 * depth)[:, None] * n
        v_rel = dv + vecmath.cross(omega[sph], lever)
        slip = v_rel - vecmath.dot(v_rel, n)[:, None] * n
        friction = _friction(scene, cp, fn, slip)
        force = force + friction
        torque = vecmath.cross(lever, friction)
    return force, torque, s


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


ALL_PAIRS = "all"
"""``pairs`` value of :func:`contact_loads`: every sphere–capsule pair of the scene."""


def contact_forces(scene: Scene, params: Params, phys: PhysState, nodes=None, held=None) -> Loads:
    """The contact stage ``fn(scene, params, phys, nodes, held) -> Loads``: every contact of
    the scene.

    ``held`` is what the contact broad phase chose at the start of the step
    (``contact.broad_phase``, :func:`mysim_jax.contact.broad_phase.broad_phase_update`):
    ``(selected, overflow)``, the sphere–capsule pairs to evaluate and whether the step
    evaluates all of them instead. None (no broad phase, or none asked): every pair.
    ``nodes`` is the ``(node_pos, node_vel)`` table (computed here if None); only
    sphere–capsule pairs read it. Sphere forces are summed with one scatter onto the
    sphere table, capsule reactions with one more onto the node table.
    """
    if held is None:
        return contact_loads(scene, params, phys, nodes)
    selected, overflow = held
    spheres = contact_loads(scene, params, phys, nodes, pairs=None)
    with jax.named_scope("capsule_contact"):
        capsules = jax.lax.cond(overflow,
                                lambda: contact_loads(scene, params, phys, nodes, pairs=ALL_PAIRS, spheres=False),
                                lambda: contact_loads(scene, params, phys, nodes, pairs=selected, spheres=False))
    return spheres + capsules


def contact_loads(scene: Scene, params: Params, phys: PhysState, nodes=None, pairs=ALL_PAIRS,
                  spheres: bool = True) -> Loads:
    """Contact loads: sphere pairs and ground (``spheres``) and the sphere–capsule pairs
    ``pairs``: :data:`ALL_PAIRS` for all of them (static indices), None for none, or a
    traced ``(k,)`` array of indices into the scene's sphere–capsule pair table (a pair
    listed twice counts twice)."""
    cs = scene.contact
    cp = params.contact
    pos, vel, omega = sphere_kinematics(scene, phys)
    n_spheres = cs.n_spheres
    rows, index = [], []
    with_torque = cs.friction and len(cs.sphere_body) > 0
    if cs.n_pairs and spheres:
        force_b, torque_a, torque_b = _pair_forces(scene, cp, pos, vel, omega)
        if with_torque:
            rows += [jnp.concatenate([-force_b, torque_a], -1), jnp.concatenate([force_b, torque_b], -1)]
        else:
            rows += [-force_b, force_b]
        index += [cs.pair_a, cs.pair_b]
    if cs.n_ground and spheres:
        force, torque = _ground_forces(scene, cp, pos, vel, omega)
        rows.append(jnp.concatenate([force, torque], -1) if with_torque else force)
        index.append(cs.ground_sphere)
    capsules = cs.n_capsule_pairs and pairs is not None
    if capsules:
        node_pos, node_vel = node_states(scene, params, phys) if nodes is None else nodes
        sph, _, end_a, end_b = capsule_pair_indices(scene, None if pairs is ALL_PAIRS else pairs)
        force, torque, s = _capsule_forces(scene, params, pos, vel, omega, node_pos, node_vel,
                                           None if pairs is ALL_PAIRS else pairs)
        rows.append(jnp.concatenate([force, torque], -1) if with_torque else force)
        index.append(sph)
        # the reaction −F shared by the capsule's end nodes: one scatter onto the node table
        on_ends = jnp.concatenate([-(1.0 - s)[:, None] * force, -s[:, None] * force], 0)
        ends = (np.concatenate([end_a, end_b]) if isinstance(end_a, np.ndarray)
                else jnp.concatenate([end_a, end_b]))
        capsule_node_force = (scatter_rows(on_ends, ends, scene.n_nodes, scene.accumulate)
                              if isinstance(ends, np.ndarray)
                              else jax.ops.segment_sum(on_ends, ends, num_segments=scene.n_nodes))
    dtype = pos.dtype
    n_pt = len(cs.sphere_point)
    if not rows:
        per_sphere = jnp.zeros((n_spheres, 6 if with_torque else 3), dtype=dtype)
    elif all(isinstance(i, (tuple, np.ndarray)) for i in index):
        # one scatter of all contributions onto the sphere table
        per_sphere = scatter_rows(jnp.concatenate(rows, 0),
                                  np.concatenate([np.asarray(i, np.int32) for i in index]),
                                  n_spheres, scene.accumulate)
    else:
        per_sphere = jax.ops.segment_sum(jnp.concatenate(rows, 0),
                                         jnp.concatenate([jnp.asarray(i, jnp.int32) for i in index]),
                                         num_segments=n_spheres)
    node_force = jnp.zeros((scene.n_nodes, 3), dtype=dtype)
    if n_pt:
        node_force = node_force.at[np.asarray(cs.sphere_point, np.int32)].add(per_sphere[:n_pt, :3])
    if capsules:
        node_force = node_force + capsule_node_force
    body_force = jnp.zeros((scene.n_bodies, 3), dtype=dtype)
    body_torque = jnp.zeros((scene.n_bodies, 3), dtype=dtype)
    if len(cs.sphere_body):
        bods = np.asarray(cs.sphere_body, np.int32)
        body_force = body_force.at[bods].add(per_sphere[n_pt:, :3])
        if with_torque:
            body_torque = body_torque.at[bods].add(quat_rotate_inv(phys.body_quat[bods], per_sphere[n_pt:, 3:]))
    return Loads(node_force=node_force, body_force=body_force, body_torque=body_torque)
