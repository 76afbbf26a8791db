"""A scripted capture team: fly the net under the predicted path of the target.

Each control period every quadrotor gets a position setpoint (its place in the start
formation around a moving formation centre ``c``):

1. **Predict.** With the target at ``p``, velocity ``v``, and the net's height ``z_n``
   (the formation's mean UAV height minus the net's start drop below the UAVs), the
   ballistic time to fall to the net is ``t* = (v_z + √(v_z² + 2 g (p_z − z_n))) / g``
   (0 once the target is at or below it; drag is ignored, which errs towards an early
   arrival). The predicted crossing point is ``p_xy + v_xy (t* + lead)``.
2. **Intercept.** The formation centre's horizontal setpoint is that point, so the net's
   centre is flown under it; the formation height is ``altitude``.
3. **Soften and stop.** When the target is within ``catch_radius`` of the net's centre
   horizontally and below the tether attachments, the formation descends by ``soften``
   metres so that the net gives way instead of bouncing the target out, and its
   horizontal setpoint is where it is (it stops chasing the target it carries).

A maneuvering target does not fall: then ``t*`` is the time a free fall *would* take,
and the team aims ahead of the target by that much of its horizontal motion. The team
knows nothing about the target's behaviour beyond its current position and velocity.

``ScriptedTeam`` is a frozen (hashable) dataclass, so it can be the ``policy`` of
:func:`mysim_jax.sim.simulate` / :func:`mysim_jax.sim.rollout` (a static argument).
``HoldTeam`` holds the start formation.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from mysim_jax.control.setpoint import Setpoint


@dataclass(frozen=True)
class HoldTeam:
    """Every quadrotor holds its start position (yaw 0)."""

    positions: tuple[tuple[float, float, float], ...]   # (n_quads, 3) m

    def __call__(self, scene, params, state) -> Setpoint:
        return Setpoint.hold(jnp.asarray(self.positions, dtype=state.phys.body_pos.dtype))


@dataclass(frozen=True)
class ScriptedTeam:
    """The intercept team of the module docstring (all lengths in m, times in s)."""

    target_body: int
    quad_bodies: tuple[int, ...]
    offsets: tuple[tuple[float, float, float], ...]   # (n_quads, 3) UAV start - formation centre
    altitude: float        # formation centre height (mean UAV height)
    net_drop: float        # net centre below the formation centre at the start
    lead: float = 0.0
    soften: float = 0.3
    catch_radius: float = 0.6

    def __call__(self, scene, params, state) -> Setpoint:
        phys = state.phys
        dtype = phys.body_pos.dtype
        quads = np.asarray(self.quad_bodies, dtype=np.int32)
        p = phys.body_pos[self.target_body]
        v = phys.body_vel[self.target_body]
        g = jnp.linalg.norm(params.gravity)
        centre = jnp.mean(phys.body_pos[quads], axis=0)
        z_net = centre[2] - self.net_drop
        drop = jnp.maximum(p[2] - z_net, 0.0)
        t_fall = (v[2] + jnp.sqrt(v[2] ** 2 + 2.0 * g * drop)) / g
        aim = p[:2] + v[:2] * (t_fall + self.lead)
        near = jnp.linalg.norm(p[:2] - centre[:2]) < self.catch_radius
        caught = near & (p[2] < centre[2]) & (p[2] > z_net - 2.0 * self.net_drop)
        # once caught, stop chasing: the target rides in the net, so aiming at it would
        # drag the team after the bowl's own offset
        aim = jnp.where(caught, centre[:2], aim)
        z = jnp.asarray(self.altitude, dtype=dtype) - jnp.where(caught, self.soften, 0.0)
        formation = jnp.concatenate([aim, z[None]]).astype(dtype)
        return Setpoint.hold(formation[None, :] + jnp.asarray(self.offsets, dtype=dtype))


def team_policy(config, scene):
    """The policy the scene's ``team:`` block asks for (None without one)."""
    team = config.team
    if team is None:
        return None
    bodies = {b.name: b for b in config.bodies}
    start = np.asarray([bodies[q.body].pos for q in config.quadrotors], float)
    if team.policy == "hold":
        return HoldTeam(positions=tuple(map(tuple, start.tolist())))
    if config.target is None:
        raise ValueError("team.policy: scripted needs a target to intercept")
    centre = start.mean(axis=0)
    altitude = centre[2] if team.altitude is None else team.altitude
    net_drop = centre[2] - (config.net.center[2] if config.net is not None else centre[2] - 1.0)
    return ScriptedTeam(
        target_body=scene.body_names.index(config.target.name),
        quad_bodies=tuple(scene.body_names.index(q.body) for q in config.quadrotors),
        offsets=tuple(map(tuple, (start - centre).tolist())),
        altitude=float(altitude), net_drop=float(net_drop),
        lead=team.lead, soften=team.soften, catch_radius=team.catch_radius,
    )
