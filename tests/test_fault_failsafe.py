"""The motor-fault failsafe between a team's actions and the UAVs' setpoints
(``env.fault_failsafe``): from the policy step a UAV's fault starts, the faulty UAV
(``faulty_uav``) or every UAV (``team``) does not descend. Small evading-drone scene
(velocity setpoints, 3 x 3 knots)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.capture import make_env

SMALL = ["net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.6", "output.plot=[target, uav0]"]
FAULT = "env.randomize.thrust_loss={fraction: {low: 0.5, high: 0.5}, time: {low: 0.2, high: 0.2}}"
SCENE = "configs/capture_env_maneuvering.yaml"


def _env(mode):
    return make_env(load_config(SCENE, SMALL + [FAULT, f"env.fault_failsafe={mode}"]))


@pytest.mark.parametrize("mode", ["faulty_uav", "team"])
def test_descents_are_floored_from_the_fault_on(mode):
    """Actions with every sign of the vertical component, before and after the fault's
    time (0.2 s: the step after 0.2 / policy_dt steps): before it they pass unchanged;
    from it the weak UAV's (or every UAV's) descent becomes 0, climbs and the horizontal
    components are untouched."""
    env, params = _env(mode)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    faulty = int(np.floor(float(state.episode.thrust_loss_uav)))
    actions = jnp.asarray([[0.3, -0.2, -0.8], [-0.5, 0.1, 0.6], [0.2, 0.2, -0.1], [0.0, -0.7, -1.0]])
    start = int(np.ceil(0.2 / env.policy_dt - 1e-6))
    for steps in (0, start - 1, start, start + 3):
        out = np.asarray(env.failsafe(actions, state.replace(steps=jnp.asarray(steps, state.steps.dtype))))
        expected = np.asarray(actions).copy()
        if steps >= start:
            weak = np.arange(4) == faulty if mode == "faulty_uav" else np.ones(4, bool)
            expected[weak, 2] = np.maximum(expected[weak, 2], 0.0)
        np.testing.assert_array_equal(out, expected)


def test_a_faulty_uav_commanded_down_stays_up_with_the_failsafe():
    """Every UAV commanded straight down at full speed: with the failsafe the faulty UAV
    (and, with ``team``, every UAV) ends the 0.6 s (a fault from 0.2 s) higher than without it, and with
    ``faulty_uav`` the healthy ones fly exactly as without it."""
    runs = {}
    for mode in ("none", "faulty_uav", "team"):
        env, params = _env(mode)
        _, state = env.reset(jax.random.PRNGKey(1), params)
        step = jax.jit(env.step_env)
        down = jnp.tile(jnp.asarray([0.0, 0.0, -1.0]), (4, 1))
        for k in range(env.max_steps):
            _, state, *_ = step(jax.random.PRNGKey(k), state, down, params)
        runs[mode] = np.asarray(state.sim.phys.body_pos[np.asarray(env.quad_bodies), 2])
        faulty = int(np.floor(float(state.episode.thrust_loss_uav)))
    healthy = np.arange(4) != faulty
    # measured: 0.86 m higher (faulty_uav), 0.86-1.16 m (team); the healthy ones within 1e-6 m
    assert runs["faulty_uav"][faulty] > runs["none"][faulty] + 0.5
    np.testing.assert_allclose(runs["faulty_uav"][healthy], runs["none"][healthy], atol=1e-3)
    assert np.all(runs["team"] > runs["none"] + 0.5)


def test_the_failsafe_needs_velocity_setpoints():
    with pytest.raises(ConfigError, match="env.fault_failsafe: team floors vertical velocity setpoints"):
        load_config("configs/capture_env_falling.yaml", ["env.fault_failsafe=team"])
    with pytest.raises(ConfigError, match="fault_failsafe"):
        load_config(SCENE, ["env.fault_failsafe=always"])
