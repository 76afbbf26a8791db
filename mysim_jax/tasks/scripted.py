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
:func:`mysim_jax.driver.simulate` / :func:`mysim_jax.sim.rollout` (a static argument).
``HoldTeam`` holds the start formation.

**Velocity setpoints** (``controller.setpoint_mode: velocity``, e.g. the training
environments): :class:`VelocityTeam` flies the same intercept with velocity commands, and
adds what a team commanding velocities can do better:

* a **drag-aware** catch point: where the target comes down to the net's current height
  (the mean height of its knots), with quadratic drag at the target's nominal mass
  (:func:`~mysim_jax.tasks.intercept.predict_catch`);
* a **lag feed-forward**: the net hangs from tethers and trails the formation while the
  formation accelerates; the team flies faster by ``lag_gain`` times the velocity by
  which the net trails it, so that the net, not only the formation, arrives under the
  catch point in time;
* **following the net** once the target is in it: the formation moves over the net's
  centre (``follow_gain``) instead of holding still, which damps the net's swing so the
  target settles sooner.

Each UAV's command is ``v_i = gain (c* + s_i − p_i) + lag_gain (v̄ − v_net)`` horizontally
(``c*`` the formation's aim, ``s_i`` its slot, ``v̄`` the team's mean velocity, ``v_net``
the knots'), and ``gain (z* − z_i)`` vertically; the environment scales it into the
action space (``v / max_speed``, clipped to ``[-1, 1]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from mysim_jax.control.setpoint import Setpoint
from mysim_jax.tasks.intercept import predict_catch


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


def _team_view(team, state):
    """What a velocity team reads from the state (world frame): the target's position and
    velocity, the UAVs' positions ``(n, 3)``, their mean position and velocity, and the
    net's knots' mean position and velocity."""
    phys = state.phys
    quads = np.asarray(team.quad_bodies, dtype=np.int32)
    knots = np.asarray(team.knot_points, dtype=np.int32)
    uav = phys.body_pos[quads]
    return (phys.body_pos[team.target_body], phys.body_vel[team.target_body], uav, jnp.mean(uav, axis=0),
            jnp.mean(phys.body_vel[quads], axis=0), jnp.mean(phys.point_pos[knots], axis=0),
            jnp.mean(phys.point_vel[knots], axis=0))


def _formation_velocities(team, formation, z, centre, uav):
    """Every UAV's command ``(n, 3)``: the formation's horizontal velocity ``formation``
    (2,) plus ``gain`` times its offset from its slot around ``centre``, and ``gain`` times
    its height error to ``z`` vertically."""
    dtype = uav.dtype
    offsets = jnp.asarray(team.offsets, dtype=dtype)
    keep = team.gain * (centre[None, :2] + offsets[:, :2] - uav[:, :2])
    vz = team.gain * (z - uav[:, 2])
    return jnp.concatenate([formation[None, :] + keep, vz[:, None]], axis=1).astype(dtype)


@dataclass(frozen=True)
class VelocityTeam:
    """The intercept team for velocity setpoints (module docstring; lengths in m, times in s)."""

    target_body: int
    quad_bodies: tuple[int, ...]
    knot_points: tuple[int, ...]                       # the net's knots (point indices)
    offsets: tuple[tuple[float, float, float], ...]   # (n_quads, 3) UAV start - formation centre
    altitude: float        # formation centre height (mean UAV height)
    net_drop: float        # net centre below the formation centre at the start
    drag_per_mass: float   # 1/m, the target's nominal k / m
    gain: float = 2.0      # 1/s, velocity per metre of position error
    lag_gain: float = 0.5
    follow_gain: float = 1.0   # 1/s, after the catch: velocity per metre of net offset
    soften: float = 0.3
    catch_radius: float = 0.6
    catch_height: float = 0.3    # a target this little above the net's centre is in it

    def velocities(self, params, state):
        """The commanded velocity of every quadrotor ``(n_quads, 3)`` m/s."""
        dtype = state.phys.body_pos.dtype
        p, v, uav, centre, v_team, c_net, v_net = _team_view(self, state)
        catch = predict_catch(p, v, c_net[2], params.gravity.astype(dtype), self.drag_per_mass)
        # in the net: near its centre horizontally and down at its height (a target still
        # falling towards the net, even below the UAVs, is not caught yet)
        near = jnp.linalg.norm(p[:2] - c_net[:2]) < self.catch_radius
        caught = near & (p[2] < c_net[2] + self.catch_height) & (p[2] > c_net[2] - 3.0 * self.net_drop)
        chase = self.gain * (catch.point[:2] - centre[:2]) + self.lag_gain * (v_team[:2] - v_net[:2])
        follow = self.follow_gain * (c_net[:2] - centre[:2])
        z = jnp.asarray(self.altitude, dtype=dtype) - jnp.where(caught, self.soften, 0.0)
        return _formation_velocities(self, jnp.where(caught, follow, chase), z, centre, uav)

    def __call__(self, scene, params, state) -> Setpoint:
        return Setpoint.from_velocity(self.velocities(params, state))


@dataclass(frozen=True)
class ChaseTeam:
    """The chase team for an evading target, with velocity setpoints (lengths in m, times
    in s): velocity feed-forward pursuit that brings the net up under the drone from
    below.

    With ``d`` the horizontal distance from the net's centre (its knots' mean) to the
    target:

    * **Horizontally** the formation's centre ``c`` flies ``v_t + pursuit_gain (p_t +
      lead v_t − c) + lag_gain (v̄ − v_net)``: the target's velocity fed forward, the gap
      to its position ``lead`` seconds ahead closed at ``pursuit_gain``, and the net's lag
      behind the formation fed forward as :class:`VelocityTeam` does. While ``d >
      climb_radius`` and the UAVs are not yet ``dive_gap`` below the target, the formation
      only matches the target's velocity: the UAVs and the tethers, which slope out from
      the net's rim to the UAVs, would otherwise sweep through the drone; the team first
      drops under it.
    * **Vertically** the formation flies so that the net's mean knot height is
      ``standoff`` below the target's centre while ``d >= climb_radius`` and ``approach``
      below once ``d <= close`` (negative: above it, so the lines reach the rotors),
      blending linearly between, and never under ``min_altitude``. While the target falls
      faster than ``fall_speed`` (entangled, its propulsion lost) and is not yet in the
      net, the formation holds its height instead of following it down.
    * **Once the target is in the net** (within ``catch_radius`` of its centre
      horizontally, below ``catch_height`` above it) the formation keeps the same
      horizontal law, which keeps the net's centre under it, and flies to ``altitude``.

    Every UAV keeps its slot around ``c`` at ``gain`` (:func:`_formation_velocities`), which
    also sets the vertical response."""

    target_body: int
    quad_bodies: tuple[int, ...]
    knot_points: tuple[int, ...]
    offsets: tuple[tuple[float, float, float], ...]
    altitude: float                # m, formation height once the target is in the net
    gain: float = 2.0
    pursuit_gain: float = 0.7      # 1/s, velocity per metre of horizontal gap to the led target
    lag_gain: float = 0.5
    lead: float = 0.2
    approach: float = -0.5
    standoff: float = 2.0
    close: float = 0.3
    climb_radius: float = 1.2
    dive_gap: float = 0.3
    min_altitude: float = 2.0      # m, the lowest formation height it commands
    catch_radius: float = 0.6
    catch_height: float = 0.3
    fall_speed: float = 0.5        # m/s, a target sinking faster has lost its propulsion

    def velocities(self, params, state):
        """The commanded velocity of every quadrotor ``(n_quads, 3)`` m/s."""
        p, v, uav, centre, v_team, c_net, v_net = _team_view(self, state)
        d = jnp.linalg.norm(p[:2] - c_net[:2])
        caught = (d < self.catch_radius) & (p[2] < c_net[2] + self.catch_height)
        chase = (v[:2] + self.pursuit_gain * (p[:2] + self.lead * v[:2] - centre[:2])
                 + self.lag_gain * (v_team[:2] - v_net[:2]))
        above_team = (centre[2] > p[2] - self.dive_gap) & (d > self.climb_radius)
        horizontal = jnp.where(above_team, v[:2], chase)
        far = jnp.clip((d - self.close) / (self.climb_radius - self.close), 0.0, 1.0)
        below = self.approach + far * (self.standoff - self.approach)
        z_chase = jnp.maximum(p[2] - below + (centre[2] - c_net[2]), self.min_altitude)
        falling = v[2] < -self.fall_speed
        z = jnp.where(caught, self.altitude, jnp.where(falling, centre[2], z_chase))
        return _formation_velocities(self, horizontal, z, centre, uav)

    def __call__(self, scene, params, state) -> Setpoint:
        return Setpoint.from_velocity(self.velocities(params, state))


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
        raise ValueError(f"team.policy: {team.policy} needs a target to intercept")
    modes = {q.controller.setpoint_mode for q in config.quadrotors if q.controller is not None}
    if team.policy == "chase":
        if modes != {"velocity"} or config.net is None:
            raise ValueError("team.policy: chase commands velocities: every quadrotor needs "
                             "controller.setpoint_mode: velocity, and the scene a net")
        net = config.net
        return ChaseTeam(
            target_body=scene.body_names.index(config.target.name),
            quad_bodies=tuple(scene.body_names.index(q.body) for q in config.quadrotors),
            knot_points=tuple(scene.point_names.index(net.knot_name(i, j))
                              for i in range(net.knots) for j in range(net.knots)),
            offsets=tuple(map(tuple, (start - start.mean(axis=0)).tolist())),
            altitude=float(start.mean(axis=0)[2] if team.altitude is None else team.altitude),
            gain=team.gain, pursuit_gain=team.pursuit_gain, lag_gain=team.lag_gain, lead=team.lead,
            approach=team.approach, standoff=team.standoff, close=team.close,
            climb_radius=team.climb_radius, dive_gap=team.dive_gap, min_altitude=team.min_altitude,
            catch_radius=team.catch_radius)
    centre = start.mean(axis=0)
    altitude = centre[2] if team.altitude is None else team.altitude
    net_drop = centre[2] - (config.net.center[2] if config.net is not None else centre[2] - 1.0)
    if modes == {"velocity"} and config.net is not None:
        net = config.net
        target = config.target
        return VelocityTeam(
            target_body=scene.body_names.index(target.name),
            quad_bodies=tuple(scene.body_names.index(q.body) for q in config.quadrotors),
            knot_points=tuple(scene.point_names.index(net.knot_name(i, j))
                              for i in range(net.knots) for j in range(net.knots)),
            offsets=tuple(map(tuple, (start - centre).tolist())),
            altitude=float(altitude), net_drop=float(net_drop),
            drag_per_mass=float(target.drag_constant / target.mass),
            gain=team.gain, lag_gain=team.lag_gain, follow_gain=team.follow_gain,
            soften=team.soften, catch_radius=team.catch_radius,
        )
    return ScriptedTeam(
        target_body=scene.body_names.index(config.target.name),
        quad_bodies=tuple(scene.body_names.index(q.body) for q in config.quadrotors),
        offsets=tuple(map(tuple, (start - centre).tolist())),
        altitude=float(altitude), net_drop=float(net_drop),
        lead=team.lead, soften=team.soften, catch_radius=team.catch_radius,
    )
