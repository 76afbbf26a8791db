"""The chase team for an evading target (mysim_jax/tasks/scripted.py, ChaseTeam): its
velocity commands on hand-built states, against the rule its docstring states."""

from __future__ import annotations

import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config import ConfigError, load_config
from mysim_jax.tasks.scripted import ChaseTeam, team_policy

CONFIG = "configs/capture_env_maneuvering.yaml"
VELOCITY = [f"quadrotors.{i}.controller.setpoint_mode=velocity" for i in range(4)]
TEAM = "team={policy: chase, gain: 1.5, lag_gain: 0.5, lead: 0.4, approach: 0.1, standoff: 1.2, close: 0.4}"


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


def test_the_chase_feeds_the_target_velocity_forward_and_keeps_the_net_below_it():
    team, scene, params, state = _team_and_state()
    quads = np.asarray(team.quad_bodies)
    knots = np.asarray(team.knot_points)
    centre = np.asarray(state.phys.body_pos[quads]).mean(0)
    net = np.asarray(state.phys.point_pos[knots]).mean(0)
    far, v = np.array([2.0, -1.0, 2.5]), np.array([0.6, 0.8, 0.0])
    still = np.asarray(team.velocities(params, _with_target(scene, state, far, np.zeros(3))))
    moving = np.asarray(team.velocities(params, _with_target(scene, state, far, v)))
    # team and net at rest in formation: every UAV gets the formation's command
    np.testing.assert_allclose(still[:, :2], np.broadcast_to(1.5 * (far[:2] - centre[:2]), (4, 2)), atol=1e-5)
    # the target's velocity fed forward, and its position lead seconds ahead aimed at
    np.testing.assert_allclose(moving[:, :2] - still[:, :2], np.broadcast_to((1.0 + 1.5 * 0.4) * v[:2], (4, 2)),
                               atol=1e-5)
    # far from under the target the net is flown standoff below it, close by approach below it
    np.testing.assert_allclose(still[:, 2], 1.5 * (far[2] - 1.2 + centre[2] - net[2] - centre[2]), atol=1e-4)
    close = np.r_[net[:2] + [0.1, 0.0], 3.5]
    up = np.asarray(team.velocities(params, _with_target(scene, state, close, np.zeros(3))))
    np.testing.assert_allclose(up[:, 2], 1.5 * (close[2] - 0.1 + centre[2] - net[2] - centre[2]), atol=1e-4)


def test_the_chase_needs_velocity_setpoints():
    cfg = load_config(CONFIG, [TEAM])
    scene, _, _ = build(cfg)
    with pytest.raises(ValueError, match="chase commands velocities"):
        team_policy(cfg, scene)
    with pytest.raises(ConfigError, match="close"):
        load_config(CONFIG, VELOCITY + ["team={policy: chase, close: 0}"])
