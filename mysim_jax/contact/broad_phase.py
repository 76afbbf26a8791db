"""Broad phase for sphere–capsule contact: an option of the contact stage
(``contact.broad_phase``), not a stage of its own.

A net's lines are hundreds of capsules, and a sphere (the target) touches a handful of
them at a time. With ``contact.broad_phase: {capsules: K, margin: m}`` the pairs are
chosen once per environment step (``sim.dt``) instead of being evaluated all in every
sub-step:

* at the start of the step (:func:`broad_phase_update`, run by
  :func:`mysim_jax.sim.step_updates` like the control stage), the surface gap of every
  sphere–capsule pair is computed (the same geometry as the narrow phase,
  :func:`mysim_jax.contact.forces.capsule_geometry`);
* each sphere keeps its K pairs of smallest gap; during the step's sub-steps the contact
  stage (:func:`mysim_jax.contact.forces.contact_forces`) evaluates only those;
* if more than K of a sphere's pairs have a gap below the margin, the step evaluates
  all pairs instead (a per-environment ``lax.cond``: batched with
  :func:`mysim_jax.core.batching.vmap`, a block of environments pays for all pairs only when
  one of them needs it).

The forces are the all-pairs forces exactly as long as no capsule outside the K closes a
gap larger than the margin within one step: the margin must exceed the largest relative
motion of a sphere and a line in ``sim.dt`` (at 0.05 m and 2 ms, 25 m/s). Two counters in
the contact stage's memory (``State.contact``, a :class:`BroadPhaseMemory`) make every
exception visible: ``overflow`` counts steps that fell back to all pairs, ``missed``
counts steps that start with a pair in contact which the previous step did not evaluate
(a contact the margin failed to foresee). The capture environment reports both in its
``info``; ``tests/test_broad_phase.py`` checks the forces against all pairs over
randomised catches.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.contact.forces import capsule_geometry, sphere_kinematics
from mysim_jax.dynamics.markers import node_states


@struct.dataclass
class BroadPhaseMemory:
    """The contact stage's memory in a scene with ``contact.broad_phase`` (``State.contact``)."""

    selected: jnp.ndarray     # (n_spheres_with_capsules * K,) int32, pairs of the last step
    overflowed: jnp.ndarray   # () bool, the last step evaluated all pairs
    overflow: jnp.ndarray     # () int32, steps that evaluated all pairs
    missed: jnp.ndarray       # () int32, steps that began with an unevaluated pair in contact


def pair_table(scene) -> np.ndarray:
    """``(n, m)`` sphere–capsule pair indices of each of the ``n`` spheres that have such
    pairs (``m`` the most any has; shorter rows padded with −1). Static."""
    cs = scene.contact
    sph = np.asarray(cs.capsule_pair_sphere)
    rows = [np.flatnonzero(sph == s) for s in np.unique(sph)]
    width = max(len(r) for r in rows)
    return np.stack([np.pad(r, (0, width - len(r)), constant_values=-1) for r in rows]).astype(np.int32)


def select_pairs(scene, params, phys):
    """``(selected, overflow, depth)``: the K pairs of smallest gap of every sphere
    ``(n * K,)``, whether some sphere has more than K pairs within the margin, and the
    penetration of every pair ``(n_capsule_pairs,)`` at ``phys``."""
    static = scene.contact.broad_phase
    table = pair_table(scene)
    k = min(static.capsules, table.shape[1])
    pos, _, _ = sphere_kinematics(scene, phys)
    node_pos, _ = node_states(scene, params, phys)
    depth = capsule_geometry(scene, params, pos, node_pos)[4]
    valid = table >= 0
    gap = jnp.where(valid, -depth[np.where(valid, table, 0)], jnp.inf)
    order = jnp.argsort(gap, axis=1)[:, :k]
    chosen = jnp.take_along_axis(jnp.asarray(np.where(valid, table, table[:, :1])), order, axis=1)
    inside = jnp.sum(gap < static.margin, axis=1)
    return chosen.reshape(-1), jnp.any(inside > k), depth


def broad_phase_update(scene, params, state):
    """``(held, memory)``: the pairs the contact stage evaluates over the step starting at
    ``state`` (``(selected, overflow)``; None in a scene without sphere–capsule pairs) and
    the broad phase's new memory. Run once per step, at its start."""
    memory = state.contact
    if not scene.contact.culls_capsules:
        return None, memory
    selected, overflow, depth = select_pairs(scene, params, state.phys)
    evaluated = jnp.zeros(depth.shape, bool).at[memory.selected].set(True) | memory.overflowed
    missed = jnp.any((depth > 0.0) & ~evaluated)
    new = BroadPhaseMemory(selected=selected, overflowed=overflow,
                           overflow=memory.overflow + overflow.astype(jnp.int32),
                           missed=memory.missed + missed.astype(jnp.int32))
    return (selected, overflow), new


def broad_phase_start(scene, params, state) -> BroadPhaseMemory:
    """The broad phase's memory at the start of a run from ``state`` (the pairs it would
    choose there, no step counted)."""
    zero = jnp.zeros((), jnp.int32)
    if not scene.contact.culls_capsules:
        return BroadPhaseMemory(selected=jnp.zeros(0, jnp.int32), overflowed=jnp.asarray(False), overflow=zero,
                                missed=zero)
    selected, overflow, _ = select_pairs(scene, params, state.phys)
    return BroadPhaseMemory(selected=selected, overflowed=overflow, overflow=zero, missed=zero)
