"""One step's verdict in the capture environment: the snapshot of the state it reached,
its success and failure flags, the potential-based shaping, the effort cost and the
outcome terms of the reward (:mod:`mysim_jax.tasks.rewards`), summed into the reward."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from mysim_jax.config.env import COST_TERMS, CRASHES, MISSES, OUTCOME_TERMS, REWARD_TERMS, SHAPING_TERMS
from mysim_jax.core.types import Params, State
from mysim_jax.dynamics.quaternion import quat_rotate
from mysim_jax.effects.entanglement import ENTANGLEMENT
from mysim_jax.tasks.capture.types import EnvParams, EnvState
from mysim_jax.tasks.rewards import Snapshot, checks, cost_terms, hold_reached, outcome_terms, potential_terms


class _Verdict(NamedTuple):
    """One step's outcome and reward (:meth:`VerdictMixin._judge`)."""

    flags: object
    held_time: jnp.ndarray
    succeeded: jnp.ndarray
    failures: dict
    crashed: jnp.ndarray
    missed: jnp.ndarray
    failed: jnp.ndarray
    steps: jnp.ndarray
    terminated: jnp.ndarray
    timeout: jnp.ndarray
    touched: jnp.ndarray
    potential: jnp.ndarray
    weighted: dict
    reward: jnp.ndarray


class VerdictMixin:
    """The rewards and episode ends of :class:`~mysim_jax.tasks.capture.env.CaptureEnv`
    (whose fields these methods read)."""

    def _judge(self, state: EnvState, sim, sim_params, params: EnvParams, dtype) -> "_Verdict":
        """The step's outcome and reward from the state it reached (``sim``)."""
        snap = self.snapshot(sim, sim_params)
        flags = self.flags(snap)
        # measured as capture_outcome measures it: from the first held sample, so a
        # hold of k consecutive held steps lasts (k - 1) policy periods
        held_time = jnp.where(flags.held & state.target_held, state.held_time + self.policy_dt, 0.0).astype(dtype)
        succeeded = flags.held & hold_reached(held_time, self.success.hold_time)
        # a step that succeeds is not a failure (the flags are exclusive in info)
        failures = {k: v & ~succeeded for k, v in flags.failures.items()}
        crashed = jnp.any(jnp.stack([failures[k] for k in CRASHES]))
        missed = jnp.any(jnp.stack([failures[k] for k in MISSES])) & ~crashed
        failed = crashed | missed
        steps = state.steps + 1
        terminated = succeeded | failed
        timeout = (steps >= self.max_steps) & ~terminated
        touched = state.touched | flags.touching
        potential = self.potential(snap, flags, touched, sim_params, params)
        # F = γ Φ(s') − Φ(s), with Φ = 0 in a state that ends the episode
        shaping = params.discount.astype(dtype) * jnp.where(terminated, 0.0, potential) - state.potential
        weighted = {k: shaping[i] for i, k in enumerate(SHAPING_TERMS)}
        costs = cost_terms(snap)
        outcomes = outcome_terms(self.n_agents, dtype, succeeded=succeeded, missed=missed, crashed=crashed)
        w = self.weights(params, dtype)
        weighted.update({k: w[k] * costs[k] for k in COST_TERMS})
        weighted.update({k: w[k] * outcomes[k] for k in OUTCOME_TERMS})
        weighted = {k: weighted[k] for k in REWARD_TERMS}
        return _Verdict(flags=flags, held_time=held_time, succeeded=succeeded, failures=failures, crashed=crashed,
                        missed=missed, failed=failed, steps=steps, terminated=terminated, timeout=timeout,
                        touched=touched, potential=potential, weighted=weighted, reward=sum(weighted.values()))

    def weights(self, params: EnvParams, dtype) -> dict:
        """Every term's weight ``name -> ()`` (REWARD_TERMS)."""
        return {k: params.weights[i].astype(dtype) for i, k in enumerate(REWARD_TERMS)}

    def potential(self, snap: Snapshot, flags, touched, sim_params: Params, params: EnvParams):
        """The weighted potential terms ``(n_shaping_terms, n_agents)`` of one state
        (SHAPING_TERMS order; :func:`~mysim_jax.tasks.rewards.potential_terms`), from its
        true state: the catch point is predicted from the target's true position and
        velocity and the net centre's height."""
        dtype = snap.uav_pos.dtype
        net_z = jnp.mean(snap.knot_pos[:, 2])
        catch = self.catch_point(snap.target_pos, snap.target_vel, net_z, self._gravity(dtype))
        terms = potential_terms(snap, flags, catch_point=catch.point, slots=jnp.asarray(self.slots, dtype),
                                scales=self.scales, touched=touched)
        w = self.weights(params, dtype)
        return jnp.stack([w[k] * terms[k] for k in SHAPING_TERMS])

    def snapshot(self, sim: State, sim_params: Params) -> Snapshot:
        phys = sim.phys
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        markers = np.asarray(self.tether_markers, dtype=np.int32)
        body_of = np.asarray(self.scene.marker_body, dtype=np.int32)[markers]
        attach = phys.body_pos[body_of] + quat_rotate(phys.body_quat[body_of], sim_params.marker_pos[markers])
        # every line node is a point mass (knots and line masses)
        a = np.asarray(self.line_nodes_a, dtype=np.int32)
        b = np.asarray(self.line_nodes_b, dtype=np.int32)
        qp = sim_params.quadrotor
        return Snapshot(
            uav_pos=phys.body_pos[quads], uav_vel=phys.body_vel[quads], uav_quat=phys.body_quat[quads],
            uav_angvel=phys.body_angvel[quads],
            rotor_fraction=sim.controller.motor_speed / qp.omega_max[:, None],
            target_pos=phys.body_pos[self.target_body], target_vel=phys.body_vel[self.target_body],
            knot_pos=phys.point_pos[knots], knot_vel=phys.point_vel[knots],
            border=phys.point_pos[np.asarray(self.border_points, dtype=np.int32)], attach=attach,
            line_a=phys.point_pos[a], line_b=phys.point_pos[b],
            entanglement=ENTANGLEMENT.memory(sim).level if ENTANGLEMENT.in_scene(self.scene) else None)

    def flags(self, snap: Snapshot):
        return checks(snap, target_radius=self.target_radius, line_radius=self.line_radius,
                      contact_margin=self.scales.contact_margin, success=self.success, failure=self.failure)
