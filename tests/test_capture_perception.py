"""The capture environment flying on estimates (``env.perception``): Gauss-Markov errors
on the UAVs' and the target's positions and velocities, in the observations and in what the
scripted team sees. Small scene as in test_capture_env.py (3 x 3 knots, 10 policy steps)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.capture import GaussMarkovLevel, make_env

SMALL = ["env={}", "net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target, uav0]"]
PERCEPTION = ["env.perception={uav_position: {sigma: 0.05, correlation_time: 0.2}, "
              "uav_velocity: {sigma: 0.02}, target_position: {sigma: 0.3, correlation_time: 0.1}, "
              "target_velocity: {sigma: 0.4, correlation_time: 0.04}}"]


@pytest.fixture(scope="module")
def envs():
    plain = make_env(load_config("configs/capture_falling.yaml", SMALL))
    zero = make_env(load_config("configs/capture_falling.yaml", SMALL + ["env.perception={}"]))
    noisy = make_env(load_config("configs/capture_falling.yaml", SMALL + PERCEPTION))
    return plain, zero, noisy


def test_zero_errors_see_exactly_the_true_states(envs):
    (env, params), (env0, params0), _ = envs
    assert not env.perception and env0.perception
    for levels in (params.perception, params0.perception):
        np.testing.assert_array_equal(np.asarray(jax.tree.leaves(levels)), 0.0)
    key = jax.random.PRNGKey(3)
    (obs, state), (obs0, state0) = jax.jit(env.reset)(key, params), jax.jit(env0.reset)(key, params0)
    assert state.perception is None and float(jnp.abs(state0.perception.uav_pos).max()) == 0.0
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(obs0))
    np.testing.assert_array_equal(np.asarray(env.scripted_actions(state, params)),
                                  np.asarray(env0.scripted_actions(state0, params0)))


def test_observations_and_scripted_team_use_the_estimates(envs):
    _, _, (env, params) = envs
    levels = params.perception      # named after the errors, from the file's entries of the same quantity
    np.testing.assert_allclose((levels.uav_pos.sigma, levels.uav_pos.rho), (0.05, np.exp(-0.04 / 0.2)),
                               rtol=1e-6)                                             # 25 Hz policy
    np.testing.assert_array_equal((levels.uav_vel.sigma, levels.uav_vel.rho), (np.float32(0.02), 0.0))  # white
    np.testing.assert_allclose((levels.target_vel.sigma, levels.target_vel.rho), (0.4, np.exp(-0.04 / 0.04)),
                               rtol=1e-6)
    reset = jax.jit(env.reset)
    obs, state = reset(jax.random.PRNGKey(1), params)
    phys, e = state.sim.phys, state.perception
    # the error levels are traced: doubling sigma doubles the draws, without a new compile
    _, twice = reset(jax.random.PRNGKey(1), params.replace(perception=jax.tree.map(
        lambda level: level.replace(sigma=2.0 * level.sigma), params.perception,
        is_leaf=lambda x: isinstance(x, GaussMarkovLevel))))
    np.testing.assert_allclose(np.asarray(twice.perception.uav_pos), 2 * np.asarray(e.uav_pos), rtol=1e-6)
    assert reset._cache_size() == 1
    quads = list(env.quad_bodies)
    pos, tpos = np.asarray(phys.body_pos)[quads], np.asarray(phys.body_pos)[env.target_body]
    vel, tvel = np.asarray(phys.body_vel)[quads], np.asarray(phys.body_vel)[env.target_body]
    est = [np.asarray(x) for x in (e.uav_pos, e.uav_vel, e.target_pos, e.target_vel)]
    assert est[0].shape == (4, 3) and est[2].shape == (3,) and np.abs(est[0]).max() > 0
    np.testing.assert_allclose(obs[:, 0:3], pos + est[0], atol=1e-6)                       # own position
    np.testing.assert_allclose(obs[:, 3:6], vel + est[1], atol=1e-6)
    # the target estimate is shared: every UAV sees the same target point
    np.testing.assert_allclose(obs[:, 13:16] + obs[:, 0:3], np.tile(tpos + est[2], (4, 1)), atol=1e-5)
    np.testing.assert_allclose(obs[:, 16:19] + obs[:, 3:6], np.tile(tvel + est[3], (4, 1)), atol=1e-5)
    # teammates at their own estimates
    np.testing.assert_allclose(obs[0, 25:28], (pos[1] + est[0][1]) - (pos[0] + est[0][0]), atol=1e-5)
    # the scripted team acts on the estimates: as if the world were where they say
    shifted = state.replace(perception=None, sim=state.sim.replace(phys=phys.replace(
        body_pos=phys.body_pos.at[jnp.asarray(quads)].add(e.uav_pos).at[env.target_body].add(e.target_pos),
        body_vel=phys.body_vel.at[jnp.asarray(quads)].add(e.uav_vel).at[env.target_body].add(e.target_vel))))
    np.testing.assert_allclose(env.scripted_actions(state, params), env.scripted_actions(shifted, params), atol=1e-6)
    assert not np.allclose(env.scripted_actions(state, params), env.scripted_actions(state.replace(perception=None),
                                                                                     params), atol=1e-4)
    # a step advances the errors by one Gauss-Markov period and observes the new ones
    key = jax.random.PRNGKey(2)
    obs, after, *_ = jax.jit(env.step)(key, state, env.scripted_actions(state, params), params)
    expected = env._step_errors(jax.random.fold_in(key, 2), state.perception, params, jnp.float32, state.sim,
                                after.sim)
    for name in ("uav_pos", "uav_vel", "target_pos", "target_vel"):
        np.testing.assert_allclose(np.asarray(getattr(after.perception, name)), np.asarray(getattr(expected, name)),
                                   rtol=0, atol=1e-7)                    # jit vs eager float32 round-off
    np.testing.assert_allclose(obs[:, 0:3], np.asarray(after.sim.phys.body_pos)[quads] + np.asarray(expected.uav_pos),
                               atol=1e-6)


def test_the_target_estimate_lags_by_its_latency(envs):
    """env.perception.target_latency: the team sees the target where it was that long ago,
    linear between the true states of the last two policy steps (plus the errors), in the
    observations and in what the scripted team sees; at an episode's first step there is no
    earlier state, so the first observation is the undelayed one."""
    _, _, (env, params) = envs
    assert float(params.target_delay) == 0.0
    half = params.replace(target_delay=jnp.asarray(0.5, jnp.float32))       # traced: no new compile
    key = jax.random.PRNGKey(4)
    (obs0, state), (obs0_half, state_half) = jax.jit(env.reset)(key, params), jax.jit(env.reset)(key, half)
    np.testing.assert_array_equal(np.asarray(obs0), np.asarray(obs0_half))
    action = env.scripted_actions(state, params)
    _, after, *_ = jax.jit(env.step)(key, state, action, params)
    obs, after_half, *_ = jax.jit(env.step)(key, state, action, half)
    np.testing.assert_array_equal(np.asarray(after.sim.phys.body_pos), np.asarray(after_half.sim.phys.body_pos))
    t = env.target_body
    e = after_half.perception
    for cols, field, err in ((slice(13, 16), "body_pos", e.target_pos), (slice(16, 19), "body_vel", e.target_vel)):
        now = np.asarray(getattr(after_half.sim.phys, field))[t]
        before = np.asarray(getattr(state.sim.phys, field))[t]
        assert np.abs(now - before).max() > 0.01                               # the target moved
        own = obs[:, 0:3] if field == "body_pos" else obs[:, 3:6]
        np.testing.assert_allclose(obs[:, cols] + own, np.tile(0.5 * (now + before) + np.asarray(err), (4, 1)),
                                   atol=2e-5)
    # the scripted team sees the same lagging target
    lagged = after_half.replace(perception=e.replace(target_pos=e.target_pos + 0.5 * (
        state.sim.phys.body_pos[t] - after_half.sim.phys.body_pos[t]), target_vel=e.target_vel + 0.5 * (
        state.sim.phys.body_vel[t] - after_half.sim.phys.body_vel[t])))
    np.testing.assert_allclose(env.scripted_actions(after_half, half), env.scripted_actions(lagged, params), atol=1e-5)
    # the file's latency, as a fraction of the 25 Hz policy period
    _, p = make_env(load_config("configs/capture_falling.yaml", SMALL + ["env.perception={target_latency: 0.03}"]))
    assert float(p.target_delay) == pytest.approx(0.75)
    with pytest.raises(ConfigError, match=r"target_latency 0.05 s is more than one policy period"):
        load_config("configs/capture_falling.yaml", SMALL + ["env.perception={target_latency: 0.05}"])


def test_errors_are_gauss_markov_with_the_configured_statistics(envs):
    """The error processes alone, 20,000 episodes for 10 policy steps: their spread stays at
    sigma (they start stationary) and their step-to-step correlation is exp(-dt / tau) (0
    when white). Measured: sigma within 0.07 %, correlation within 0.003."""
    _, _, (env, params) = envs
    start = params.start

    def episode(key):
        def body(e, k):
            e = env._step_errors(k, e, params, jnp.float32, start, start)
            return e, e
        first = env._draw_errors(key, params, jnp.float32, start)
        return first, jax.lax.scan(body, first, jax.random.split(jax.random.fold_in(key, 1), 10))[1]

    first, steps = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(0), 20_000))
    for name in ("uav_pos", "uav_vel", "target_pos", "target_vel"):
        sigma, rho = (float(x) for x in (getattr(params.perception, name).sigma, getattr(params.perception, name).rho))
        e = np.concatenate([np.asarray(getattr(first, name))[:, None], np.asarray(getattr(steps, name))], axis=1)
        e = e.reshape(e.shape[0], e.shape[1], -1)                # (episodes, 11 times, values)
        assert e.std() == pytest.approx(sigma, rel=0.01), name
        lag1 = np.sum(e[:, 1:] * e[:, :-1]) / np.sum(e[:, :-1] ** 2)
        assert lag1 == pytest.approx(rho, abs=0.03), name


def test_target_dropouts_have_the_declared_statistics_and_coast(envs):
    """env.perception.target_dropout: the loss chain alone over 4,000 episodes of 150 policy
    steps lost the declared fraction of the time (after its start, seen, has faded) with
    losses of the declared mean duration; while lost, the observations and the scripted team
    see the last estimate coasted under gravity (the falling target), and the estimate
    returns when the target is seen again. The rates are traced: no new compile."""
    _, _, (env, params) = envs
    _, p = make_env(load_config("configs/capture_falling.yaml", SMALL + [
        "env.perception={target_dropout: {fraction: 0.2, mean_duration: 0.2}}"]))
    dt = env.policy_dt
    p_regain = 1 - np.exp(-dt / 0.2)
    np.testing.assert_allclose(np.asarray(p.target_dropout), (p_regain * 0.25, p_regain), rtol=1e-6)
    lossy = params.replace(target_dropout=p.target_dropout)
    start = params.start

    def episode(key):
        def body(e, k):
            e = env._step_errors(k, e, lossy, jnp.float32, start, start)
            return e, e.target_lost
        first = env._draw_errors(key, lossy, jnp.float32, start)
        return jax.lax.scan(body, first, jax.random.split(jax.random.fold_in(key, 1), 150))[1]

    lost = np.asarray(jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(0), 4_000)))
    assert lost[:, 75:].mean() == pytest.approx(0.2, abs=0.01)
    ended = np.sum(lost[:, :-1] & ~lost[:, 1:])
    assert dt / (ended / np.sum(lost[:, :-1])) == pytest.approx(dt / p_regain, rel=0.03)   # mean loss, s
    # in an episode: lost at the first step (p_lose = 1), regained at the second (p_regain = 1)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    _, state = reset(jax.random.PRNGKey(5), params)
    always = params.replace(target_dropout=jnp.asarray([1.0, 0.0], jnp.float32))
    key = jax.random.PRNGKey(6)
    obs, after, *_ = step(key, state, env.scripted_actions(state, params), always)
    e0, e = state.perception, after.perception
    assert bool(e.target_lost) and int(e.target_lost_steps) == 1
    np.testing.assert_array_equal(np.asarray(e.target_last_pos), np.asarray(e0.target_last_pos))
    t = np.float32(dt)
    g = np.asarray(env.gravity, np.float32)
    coast_pos = np.asarray(e0.target_last_pos) + np.asarray(e0.target_last_vel) * t + 0.5 * g * t * t
    coast_vel = np.asarray(e0.target_last_vel) + g * t
    np.testing.assert_allclose(obs[:, 13:16] + obs[:, 0:3], np.tile(coast_pos, (4, 1)), atol=1e-5)
    np.testing.assert_allclose(obs[:, 16:19] + obs[:, 3:6], np.tile(coast_vel, (4, 1)), atol=1e-5)
    seen = np.asarray(after.sim.phys.body_pos)[env.target_body] + np.asarray(e.target_pos)
    assert np.abs(coast_pos - seen).max() > 1e-3                   # the coasted estimate is not the seen one
    phys = after.sim.phys
    # the scripted team sees the coasted target: as if it were seen there
    coasted = after.replace(perception=e.replace(target_lost=jnp.zeros((), bool),
                                                 target_pos=jnp.asarray(coast_pos) - phys.body_pos[env.target_body],
                                                 target_vel=jnp.asarray(coast_vel) - phys.body_vel[env.target_body]))
    np.testing.assert_allclose(env.scripted_actions(after, always), env.scripted_actions(coasted, params), atol=1e-5)
    regain = params.replace(target_dropout=jnp.asarray([0.0, 1.0], jnp.float32))
    obs2, again, *_ = step(key, after, env.scripted_actions(after, regain), regain)
    assert not bool(again.perception.target_lost) and int(again.perception.target_lost_steps) == 0
    seen2 = np.asarray(again.sim.phys.body_pos)[env.target_body] + np.asarray(again.perception.target_pos)
    np.testing.assert_allclose(obs2[:, 13:16] + obs2[:, 0:3], np.tile(seen2, (4, 1)), atol=1e-5)
    np.testing.assert_allclose(np.asarray(again.perception.target_last_pos), seen2, atol=1e-6)
    assert step._cache_size() == 1
    with pytest.raises(ConfigError, match=r"target_dropout.*lengthen mean_duration"):
        load_config("configs/capture_falling.yaml", SMALL + [
            "env.perception={target_dropout: {fraction: 0.6, mean_duration: 0.01}}"])


@pytest.mark.parametrize("override, message", [
    ("env.perception={uav_position: {sigma: -0.1}}", r"env.perception.uav_position.sigma"),
    ("env.perception={target_position: {sigma: 0.1, correlation_tme: 1.0}}", r"correlation_tme"),
    ("env.perception={uav_attitude: {sigma: 0.1}}", r"uav_attitude"),
])
def test_bad_perception_blocks_name_the_field(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config("configs/capture_falling.yaml", SMALL + [override])


def test_per_episode_scale_multiplies_every_sigma(envs):
    """``env.perception.scale``: each episode draws one factor on the four errors' sigma;
    a fixed factor of 1 (the default) is exactly the errors without it."""
    _, _, (env, params) = envs
    np.testing.assert_array_equal(np.asarray(params.perception_scale), [1.0, 1.0])
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    key = jax.random.PRNGKey(4)
    fields = ("uav_pos", "uav_vel", "target_pos", "target_vel")

    def errors(p):
        _, s = reset(key, p)
        first = s.perception
        s = step(jax.random.PRNGKey(5), s, env.scripted_actions(s, p), p)[1]
        return first, s.perception

    one, one_next = errors(params)
    assert float(one.scale) == 1.0
    fixed3, fixed3_next = errors(params.replace(perception_scale=jnp.asarray([3.0, 3.0])))
    assert float(fixed3.scale) == 3.0 and float(fixed3_next.scale) == 3.0      # kept over the episode
    for name in fields:      # the same draws, three times the size, at the reset and after a step
        np.testing.assert_allclose(getattr(fixed3, name), 3 * np.asarray(getattr(one, name)), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(getattr(fixed3_next, name), 3 * np.asarray(getattr(one_next, name)),
                                   rtol=1e-4, atol=1e-6)
    # a range: one factor per episode, inside it, different between episodes
    ranged = params.replace(perception_scale=jnp.asarray([0.5, 2.5]))
    keys = jax.random.split(jax.random.PRNGKey(6), 256)
    scales = np.asarray(jax.vmap(lambda k: reset(k, ranged)[1].perception.scale)(keys))
    assert scales.min() >= 0.5 and scales.max() <= 2.5 and scales.std() > 0.4    # uniform: std 0.58
    assert reset._cache_size() == 1                                            # traced: no new compile


def test_scale_in_the_scene_file():
    config = load_config("configs/capture_falling.yaml", SMALL + [PERCEPTION[0][:-1] + ", scale: {low: 0.5, "
                                                                                       "high: 2.0}}"])
    _, params = make_env(config)
    np.testing.assert_allclose(np.asarray(params.perception_scale), [0.5, 2.0])
    with pytest.raises(ConfigError, match="scale"):
        load_config("configs/capture_falling.yaml", SMALL + ["env.perception={scale: {low: 2.0, high: 1.0}}"])
    with pytest.raises(ConfigError, match="scale"):
        load_config("configs/capture_falling.yaml", SMALL + ["env.perception={scale: {low: -1.0, high: 1.0}}"])
