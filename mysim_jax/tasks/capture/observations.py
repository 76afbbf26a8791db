"""What the capture environment's agents observe (:meth:`ObservationsMixin._observe`,
``(n_agents, obs_size)``) and the noise-free global state its centralised critic gets
(:meth:`ObservationsMixin.global_state`), with the predicted catch point both carry
(:meth:`ObservationsMixin.catch_point`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import rng
from mysim_jax.tasks.capture.types import EnvParams, EnvState
from mysim_jax.tasks.intercept import CatchPoint, predict_catch

# the catch-point features of an observation: the catch point relative to the agent's
# slot position (3, in units of CATCH_LENGTH_SCALE) and the time to it (1, in units of
# CATCH_TIME_SCALE)
CATCH_FEATURES = 4
CATCH_LENGTH_SCALE = 2.0    # m
CATCH_TIME_SCALE = 1.0      # s


class ObservationsMixin:
    """The observations of :class:`~mysim_jax.tasks.capture.env.CaptureEnv` (whose fields
    these methods read)."""

    def _gravity(self, dtype):
        return jnp.asarray(self.gravity, dtype)

    def catch_point(self, target_pos, target_vel, net_z, gravity) -> CatchPoint:
        """Where and when the target meets the net's height ``net_z`` (m), as the team can
        predict it: a falling target's drag-aware fall with the nominal drag per mass
        (:func:`~mysim_jax.tasks.intercept.predict_catch`); a maneuvering target's current
        position (it does not fall; ``time`` 0)."""
        if self.falling:
            return predict_catch(target_pos, target_vel, net_z, gravity, self.target_drag_per_mass)
        return CatchPoint(point=target_pos, time=jnp.zeros((), target_pos.dtype), velocity=target_vel,
                          crossed=jnp.ones((), bool))

    def _observe(self, key, state: EnvState, params: EnvParams):
        phys = state.sim.phys
        dtype = phys.body_pos.dtype
        n = self.n_agents
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        noise = jax.tree.map(lambda s: s.astype(dtype), state.episode.noise)
        est_pos, est_vel, est_tpos, est_tvel = self.estimates(state, params)
        if self.observation_noise:
            xi = rng.normal_each(jax.random.split(key, 4), [(n, 3)] * 4, dtype)
            pos = est_pos + noise.uav_pos * xi[0]
            vel = est_vel + noise.uav_vel * xi[1]
            tpos = est_tpos + noise.target_pos * xi[2]
            tvel = est_tvel + noise.target_vel * xi[3]
        else:   # sigma is 0 in every episode: the same values without the draws' code
            pos, vel, tpos, tvel = (jnp.broadcast_to(x, (n, 3)) for x in (est_pos, est_vel, est_tpos, est_tvel))
        c_net = jnp.mean(phys.point_pos[knots], axis=0)
        v_net = jnp.mean(phys.point_vel[knots], axis=0)
        # each agent's own prediction of the catch point, from its measurement of the target
        gravity = self._gravity(dtype)
        catch = jax.vmap(lambda p, v: self.catch_point(p, v, c_net[2], gravity))(tpos, tvel)
        slots = jnp.asarray(self.slots, dtype)
        to_slot = (catch.point + slots - pos) / CATCH_LENGTH_SCALE
        catch_time = catch.time[:, None] / CATCH_TIME_SCALE
        # teammates j != i, relative to i, in a fixed order per agent
        others = np.asarray([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int32).reshape(n, n - 1)
        mates = jnp.concatenate([est_pos[others] - pos[:, None, :], est_vel[others] - vel[:, None, :]], axis=-1)
        left = 1.0 - state.steps.astype(dtype) / self.max_steps
        parts = [
            pos, vel, phys.body_quat[quads], phys.body_angvel[quads],
            tpos - pos, tvel - vel,
            c_net[None, :] - pos, v_net[None, :] - vel,
            mates.reshape(n, 6 * (n - 1)),
            to_slot, catch_time,
            jnp.eye(n, dtype=dtype),
            jnp.broadcast_to(left, (n, 1)),
        ]
        if self.observe_top_thrust:
            # own first, then the teammates in the order of ``mates``
            top = self.top_thrust_fractions(state.episode, state.steps, dtype)
            parts.append(jnp.concatenate([top[:, None], top[others]], axis=-1))
        obs = jnp.concatenate(parts, axis=-1)
        return jnp.where(jnp.isfinite(obs), obs, 0.0)

    def global_state(self, state: EnvState):
        """The noise-free global state ``(state_size,)`` for a centralised critic."""
        phys = state.sim.phys
        dtype = phys.body_pos.dtype
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        knots = np.asarray(self.knot_points, dtype=np.int32)
        uav = jnp.concatenate([phys.body_pos[quads], phys.body_vel[quads], phys.body_quat[quads],
                               phys.body_angvel[quads]], axis=-1).reshape(-1)
        left = 1.0 - state.steps.astype(dtype) / self.max_steps
        c_net = jnp.mean(phys.point_pos[knots], axis=0)
        catch = self.catch_point(phys.body_pos[self.target_body], phys.body_vel[self.target_body], c_net[2],
                                 self._gravity(dtype))
        centre = jnp.mean(phys.body_pos[quads], axis=0)
        out = jnp.concatenate([uav, phys.body_pos[self.target_body], phys.body_vel[self.target_body],
                               c_net, jnp.mean(phys.point_vel[knots], axis=0),
                               (catch.point - centre) / CATCH_LENGTH_SCALE, catch.time[None] / CATCH_TIME_SCALE,
                               left[None]]
                              + ([self.top_thrust_fractions(state.episode, state.steps, dtype)]
                                 if self.observe_top_thrust else []))
        return jnp.where(jnp.isfinite(out), out, 0.0)
