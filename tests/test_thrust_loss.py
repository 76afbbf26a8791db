"""A motor fault in the capture environment (``env.randomize.thrust_loss``): one UAV, drawn
per episode, keeps only a fraction of its maximum thrust from a drawn time on. Small scene
as in test_capture_perception.py (3 x 3 knots, 25 Hz policy)."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.capture import make_env

SMALL = ["env={}", "net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target, uav0]"]
FAULT = "env.randomize.thrust_loss={fraction: {low: 0.25, high: 0.25}, time: {low: 0.1, high: 0.3}}"


@pytest.fixture(scope="module")
def faulty():
    return make_env(load_config("configs/capture_falling.yaml", SMALL + [FAULT]))


def test_the_fault_cuts_one_uavs_top_speed_from_its_time_on(faulty):
    env, params = faulty
    assert env.thrust_loss
    episodes = jax.vmap(env.draw_episode, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 4000),
                                                             params.ranges)
    uav = np.floor(np.asarray(episodes.thrust_loss_uav)).astype(int)
    # every UAV is the faulty one about as often (4000 draws: one standard deviation 0.007)
    np.testing.assert_allclose(np.bincount(uav, minlength=4) / 4000, 0.25, atol=0.03)
    assert np.all(np.asarray(episodes.thrust_fraction) == np.float32(0.25))
    t = np.asarray(episodes.thrust_loss_time)
    assert 0.1 <= t.min() < 0.12 and 0.28 < t.max() <= 0.3
    ep = jax.tree.map(lambda x: x[0], episodes)
    nominal = np.asarray(params.sim.quadrotor.omega_max)
    sim_params = env.episode_params(params, ep)
    for steps in range(10):
        top = np.asarray(env.faulted(sim_params, ep, jnp.asarray(steps)).quadrotor.omega_max)
        expected = nominal.copy()
        if steps * env.policy_dt >= float(ep.thrust_loss_time):
            expected[uav[0]] *= 0.5                                           # √0.25
        np.testing.assert_allclose(top, expected, rtol=1e-6)


def test_a_uav_without_thrust_falls_and_the_others_fly_on(faulty):
    """Total loss from the start for one UAV: its rotors spin down and it sinks below the
    height it keeps without the fault; the other three's top speed is the nominal one. The
    same compiled step flies both (the fault's draws are traced)."""
    env, params = faulty
    stop = params.ranges.low.replace(thrust_fraction=jnp.float32(0.0), thrust_loss_time=jnp.float32(0.0),
                                     thrust_loss_uav=jnp.float32(2.0))
    fault = params.replace(ranges=params.ranges.replace(low=stop, high=stop))
    healthy = params.replace(ranges=params.ranges.replace(
        low=stop.replace(thrust_fraction=jnp.float32(1.0)), high=stop.replace(thrust_fraction=jnp.float32(1.0))))
    reset, step = jax.jit(env.reset), jax.jit(env.step_env)
    key = jax.random.PRNGKey(1)
    heights = {}
    for name, p in (("fault", fault), ("healthy", healthy)):
        _, state = reset(key, p)
        for _ in range(8):                                                   # 0.32 s
            _, state, *_ = step(key, state, jnp.zeros(env.action_shape), p)
        quads = list(env.quad_bodies)
        heights[name] = np.asarray(state.sim.phys.body_pos)[quads, 2]
        speeds = np.asarray(state.sim.controller.motor_speed)
        if name == "fault":
            assert speeds[2].max() < 0.2 * float(params.sim.quadrotor.omega_max[2])
            others = [0, 1, 3]
            assert speeds[others].max() <= float(params.sim.quadrotor.omega_max.max()) * (1 + 1e-6)
    assert step._cache_size() == 1
    drop = heights["healthy"] - heights["fault"]
    assert drop[2] > 0.1, drop                       # the faulty UAV sank (m)
    assert np.abs(np.delete(drop, 2)).max() < 0.5 * drop[2], drop


def test_a_scene_without_the_fault_draws_nothing_for_it():
    """Without env.randomize.thrust_loss the episode holds no fault fields (no draws, the
    environment state of a scene without the effect) and the step has no fault code."""
    env, params = make_env(load_config("configs/capture_falling.yaml", SMALL))
    assert not env.thrust_loss
    for ep in (params.ranges.low, params.ranges.high):
        assert ep.thrust_fraction is None and ep.thrust_loss_time is None and ep.thrust_loss_uav is None


def test_bad_fault_ranges_are_refused():
    with pytest.raises(ConfigError, match="a fraction of the nominal thrust is at most 1"):
        load_config("configs/capture_falling.yaml",
                    SMALL + ["env.randomize.thrust_loss={fraction: {low: 0.5, high: 1.5}, time: {low: 0, high: 1}}"])
    with pytest.raises(ConfigError, match="empty range"):
        load_config("configs/capture_falling.yaml",
                    SMALL + ["env.randomize.thrust_loss={fraction: {low: 0.5, high: 0.5}, time: {low: 2, high: 1}}"])
