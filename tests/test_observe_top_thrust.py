"""Every UAV's top thrust in the observations (``env.observe_top_thrust``) and a saved
policy widened to read it (:func:`mysim_jax.mappo.policies.widen_policy`). Small scene as
in test_thrust_loss.py (3 x 3 knots, 25 Hz policy)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import load_config
from mysim_jax.tasks.capture import make_env

SMALL = ["env={}", "net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target, uav0]"]
FAULT = "env.randomize.thrust_loss={fraction: {low: 0.4, high: 0.4}, time: {low: 0.1, high: 0.1}}"
OBSERVE = "env.observe_top_thrust=true"


@pytest.fixture(scope="module")
def envs():
    """(without the features, with them), both with the same motor fault."""
    return (make_env(load_config("configs/capture_falling.yaml", SMALL + [FAULT])),
            make_env(load_config("configs/capture_falling.yaml", SMALL + [FAULT, OBSERVE])))


def test_the_features_are_each_uavs_top_thrust_own_first(envs):
    """The observation is the one without the option with n features appended: the UAV's
    own top-thrust fraction, then its teammates' in the teammates' order; 1 before the
    fault's time (0.1 s: from the third policy step at 25 Hz), the faulty UAV's 0.4 from
    it on; the critic's state ends with all four in UAV order."""
    (plain, p_plain), (env, params) = envs
    n = env.n_agents
    assert env.obs_size == plain.obs_size + n and env.state_size == plain.state_size + n
    key = jax.random.PRNGKey(3)
    obs0, s0 = plain.reset(key, p_plain)
    obs, state = env.reset(key, params)
    np.testing.assert_array_equal(np.asarray(obs[:, :plain.obs_size]), np.asarray(obs0))
    # the same episode is drawn (scripts/pair.py pairs evaluations that differ in the option)
    for a, b in zip(jax.tree.leaves(state.episode), jax.tree.leaves(s0.episode)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    faulty = int(np.floor(float(state.episode.thrust_loss_uav)))
    step = jax.jit(env.step)
    actions = jnp.zeros(env.action_shape)
    seen = []
    for k in range(4):
        top = np.asarray(obs[:, plain.obs_size:])
        full = np.asarray(env.global_state(state))[-n:]
        expected = np.ones(n, np.float32)
        if k * env.policy_dt >= 0.1 - 1e-6:
            expected[faulty] = 0.4
        np.testing.assert_allclose(full, expected, rtol=1e-6)
        for i in range(n):
            mates = [j for j in range(n) if j != i]
            np.testing.assert_allclose(top[i], expected[[i] + mates], rtol=1e-6)
        seen.append(float(full[faulty]))
        obs, state, *_ = step(jax.random.PRNGKey(k), state, actions, params)
    assert seen[0] == 1.0 and seen[-1] == pytest.approx(0.4)


def test_the_layout_names_the_features_and_without_a_fault_they_are_one():
    from mysim_jax.tasks.contract import observation_layout

    env, params = make_env(load_config("configs/capture_falling.yaml", SMALL + [OBSERVE]))
    layout = observation_layout(env)
    assert layout[-1] == ("top_thrust_fraction_own_then_teammates_x4", 4)
    assert sum(w for _, w in layout) == env.obs_size
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    np.testing.assert_array_equal(np.asarray(obs[:, -4:]), 1.0)
    np.testing.assert_array_equal(np.asarray(env.global_state(state))[-4:], 1.0)


def _saved_policy(env, params, key):
    """A policy.json record and arrays of a random actor trained (so to speak) on ``env``."""
    from mysim_jax.mappo.networks import Actor
    from mysim_jax.tasks.contract import environment_contract

    actor = Actor(action_dim=3, hidden=(16, 16))
    k1, k2, k3 = jax.random.split(key, 3)
    variables = actor.init(k1, jnp.zeros((env.obs_size,)))
    arrays = {"actor": jax.tree.map(np.asarray, variables),
              "obs_mean": np.asarray(jax.random.normal(k2, (env.obs_size,))),
              "obs_var": np.asarray(jax.random.uniform(k3, (env.obs_size,), minval=0.5, maxval=2.0))}
    meta = {"kind": "mappo", "obs_size": env.obs_size, "action_shape": list(env.action_shape), "hidden": [16, 16],
            "environment": environment_contract(env, params)}
    return actor, meta, arrays


def test_a_policy_widened_to_the_new_features_acts_as_before(envs):
    """A policy trained without the features, widened: its record passes the check on the
    environment with them, and its actions there are the ones it takes on the same state
    without them (zero weights on the features) whatever their values; the starting
    policy of a fine-tuning (``algo.init: policy``) is that policy, its anchor too. The
    other way round (a policy with the features on an environment without) is refused."""
    from mysim_jax.mappo.algorithm import warm_start
    from mysim_jax.mappo.config import AlgoConfig
    from mysim_jax.mappo.policies import PolicyError, check_trained_on, widen_policy
    from mysim_jax.mappo.shac import make_trainer

    (plain, p_plain), (env, params) = envs
    actor, meta, arrays = _saved_policy(plain, p_plain, jax.random.PRNGKey(1))
    with pytest.raises(PolicyError, match="observations of size"):
        check_trained_on(meta, env, params, "p")
    wide_meta, wide = widen_policy(meta, arrays, env, params, "p")
    check_trained_on(wide_meta, env, params, "p")
    assert wide_meta["widened_from_obs_size"] == plain.obs_size and wide_meta["obs_size"] == env.obs_size
    assert widen_policy(meta, None, env, params, "p")[0] == wide_meta
    obs, _ = env.reset(jax.random.PRNGKey(5), params)
    obs = np.array(obs)
    obs[:, plain.obs_size:] = [0.3, 1.0, 0.7, 0.5]          # any values: they do not count yet

    def means(a, o):
        x = (o - a["obs_mean"]) / np.sqrt(a["obs_var"] + 1e-8)
        return np.asarray(actor.apply(a["actor"], x)[0])

    np.testing.assert_allclose(means(wide, obs), means(arrays, obs[:, :plain.obs_size]), rtol=1e-5, atol=1e-6)
    # the fine-tuning's start: the widened actor and normalisation, the anchor on them
    trainer = make_trainer(AlgoConfig(init="policy", init_policy="x", hidden=[16, 16], num_envs=4, num_steps=2,
                                      num_minibatches=2, total_env_steps=8), env, params)
    ts, _ = warm_start(trainer, trainer._init_state(jax.random.PRNGKey(0)), jax.random.PRNGKey(1), (wide_meta, wide))
    np.testing.assert_array_equal(np.asarray(ts.params["actor"]["params"]["Dense_0"]["kernel"]),
                                  wide["actor"]["params"]["Dense_0"]["kernel"])
    np.testing.assert_array_equal(np.asarray(ts.anchor["obs_var"]), wide["obs_var"])
    # a policy that reads the features cannot fly without them, and is not "widened" there
    _, meta_b, arrays_b = _saved_policy(env, params, jax.random.PRNGKey(2))
    assert widen_policy(meta_b, arrays_b, plain, p_plain, "q") == (meta_b, arrays_b)
    with pytest.raises(PolicyError, match="observations of size"):
        check_trained_on(meta_b, plain, p_plain, "q")
