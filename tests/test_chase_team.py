"""The chase team for an evading target (mysim_jax/tasks/scripted.py, ChaseTeam): its
velocity commands on hand-built states, against the rule its docstring states."""

from __future__ import annotations

import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.scripted import ChaseTeam, team_policy

CONFIG = "configs/capture_env_maneuvering.yaml"
VELOCITY = [f"quadrotors.{i}.controller.setpoint_mode=velocity" for i in range(4)]
TEAM = ("team={policy: chase, gain: 1.5, pursuit_gain: 0.8, lag_gain: 0.5, lead: 0.4, approach: -0.5, "
        "standoff: 1.2, close: 0.3, climb_radius: 1.0, dive_gap: 0.3, min_altitude: 2.0, altitude: 3.5}")


def _team_and_state():
    cfg = load_config(CONFIG, VELOCITY + [TEAM])
    scene, params, state = build(cfg)
    team = team_policy(cfg, scene)
    assert isinstance(team, ChaseTeam)
    return team, scene, params, state


def _with_target(scene, state, pos, vel):
    b = scene.body_names.index("target")
    phys = state.phys.replace(body_pos=state.phys.body_pos.at[b].set(np.asarray(pos, np.float32)),
                              body_vel=state.phys.body_vel.at[b].set(np.asarray(vel, np.float32)))
    return state.replace(phys=phys)


def _formation(team, state):
    quads, knots = np.asarray(team.quad_bodies), np.asarray(team.knot_points)
    return np.asarray(state.phys.body_pos[quads]).mean(0), np.asarray(state.phys.point_pos[knots]).mean(0)


def test_the_chase_feeds_the_target_velocity_forward_and_keeps_the_net_below_it():
    team, scene, params, state = _team_and_state()
    centre, net = _formation(team, state)
    hang = centre[2] - net[2]                       # the net's mean height below the formation
    # a far target above the UAVs (by more than dive_gap): the gap to its led position is closed
    far, v = np.array([2.0, -1.0, 5.0]), np.array([0.6, 0.8, 0.0])
    still = np.asarray(team.velocities(params, _with_target(scene, state, far, np.zeros(3))))
    moving = np.asarray(team.velocities(params, _with_target(scene, state, far, v)))
    # team and net at rest in formation: every UAV gets the formation's command
    np.testing.assert_allclose(still[:, :2], np.broadcast_to(0.8 * (far[:2] - centre[:2]), (4, 2)), atol=1e-5)
    # the target's velocity fed forward, and its position lead seconds ahead aimed at
    np.testing.assert_allclose(moving[:, :2] - still[:, :2], np.broadcast_to((1.0 + 0.8 * 0.4) * v[:2], (4, 2)),
                               atol=1e-5)
    # far from under the target the net is flown standoff below it ...
    np.testing.assert_allclose(still[:, 2], 1.5 * (far[2] - 1.2 + hang - centre[2]), atol=1e-4)
    # ... close by approach below it (above it: approach < 0), halfway between at mid-distance
    close = np.r_[net[:2] + [0.1, 0.0], 3.5]
    up = np.asarray(team.velocities(params, _with_target(scene, state, close, np.zeros(3))))
    np.testing.assert_allclose(up[:, 2], 1.5 * (close[2] + 0.5 + hang - centre[2]), atol=1e-4)
    mid = np.r_[net[:2] + [0.65, 0.0], 3.5]
    half = np.asarray(team.velocities(params, _with_target(scene, state, mid, np.zeros(3))))
    np.testing.assert_allclose(half[:, 2], 1.5 * (mid[2] - 0.35 + hang - centre[2]), atol=1e-4)


def test_the_chase_drops_under_a_far_target_before_closing_in_and_stays_above_min_altitude():
    team, scene, params, state = _team_and_state()
    centre, net = _formation(team, state)
    # a far target below the UAVs: only its velocity is matched, the formation descends first,
    # to the lowest formation height here (2.2 - 1.2 + hang < 2.0)
    low, v = np.array([2.0, -1.0, 2.2]), np.array([0.6, 0.8, 0.0])
    cmd = np.asarray(team.velocities(params, _with_target(scene, state, low, v)))
    np.testing.assert_allclose(cmd[:, :2], np.broadcast_to(v[:2], (4, 2)), atol=1e-5)
    assert low[2] - 1.2 + (centre[2] - net[2]) < 2.0
    np.testing.assert_allclose(cmd[:, 2], 1.5 * (2.0 - centre[2]), atol=1e-4)
    # the same target within climb_radius (inside the tethers' slope) is closed in on
    near = np.r_[net[:2] + [0.8, 0.0], 2.2]
    cmd = np.asarray(team.velocities(params, _with_target(scene, state, near, np.zeros(3))))
    np.testing.assert_allclose(cmd[:, :2], np.broadcast_to(0.8 * (near[:2] - centre[:2]), (4, 2)), atol=1e-5)


def test_the_chase_holds_its_height_under_a_falling_target_and_flies_to_altitude_after_the_catch():
    team, scene, params, state = _team_and_state()
    centre, net = _formation(team, state)
    falling = np.r_[net[:2] + [0.5, 0.0], net[2] + 1.0]
    cmd = np.asarray(team.velocities(params, _with_target(scene, state, falling, [0.0, 0.0, -1.0])))
    np.testing.assert_allclose(cmd[:, 2], 0.0, atol=1e-5)
    rising = np.asarray(team.velocities(params, _with_target(scene, state, falling, [0.0, 0.0, -0.2])))
    assert np.all(np.abs(rising[:, 2]) > 0.1)       # not falling: it climbs to meet it
    in_net = np.r_[net[:2] + [0.2, 0.0], net[2] + 0.1]
    cmd = np.asarray(team.velocities(params, _with_target(scene, state, in_net, np.zeros(3))))
    np.testing.assert_allclose(cmd[:, 2], 1.5 * (3.5 - centre[2]), atol=1e-4)
    np.testing.assert_allclose(cmd[:, :2], np.broadcast_to(0.8 * (in_net[:2] - centre[:2]), (4, 2)), atol=1e-5)


def test_the_chase_needs_velocity_setpoints():
    cfg = load_config(CONFIG, [f"quadrotors.{i}.controller.setpoint_mode=position" for i in range(4)] + [TEAM])
    scene, _, _ = build(cfg)
    with pytest.raises(ValueError, match="chase commands velocities"):
        team_policy(cfg, scene)
    with pytest.raises(ConfigError, match="close"):
        load_config(CONFIG, VELOCITY + ["team={policy: chase, close: 0}"])
    with pytest.raises(ConfigError, match="team.climb_radius: 0.3 m must be larger than team.close"):
        load_config(CONFIG, VELOCITY + ["team={policy: chase, close: 0.4, climb_radius: 0.3}"])
