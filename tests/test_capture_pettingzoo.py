"""The PettingZoo wrapper of the capture environment (mysim_jax/tasks/pettingzoo_env.py).

A small, fast scene: capture_falling with a 3 x 3 net, one mass per tether and a 0.4 s
episode (10 policy steps at 25 Hz), so an episode always ends by truncation. The
wrappers built here share one compiled reset and step (equal static environments).
"""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from mysim_jax.config.scene import load_config
from mysim_jax.tasks.pettingzoo_env import CaptureParallelEnv

from conftest import CONFIGS

SMALL = ["env={}", "net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target, uav0]"]   # the file plots knot net_k5_5, which a 3 x 3 net lacks
N_STEPS = 10   # t_end / (1 / policy_rate)


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIGS / "capture_falling.yaml", SMALL)


@pytest.fixture(scope="module")
def pz_env(config):
    env = CaptureParallelEnv(config)
    yield env
    env.close()


def zeros(env):
    return {a: np.zeros(3, np.float32) for a in env.agents}


def rollout(env, seed, actions, n_steps):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(n_steps):
        obs, *_ = env.step(actions)
        out.append(obs)
    return out


def test_parallel_api(pz_env):
    parallel_api_test(pz_env, num_cycles=2 * N_STEPS)


def test_parallel_seed(config):
    parallel_seed_test(lambda: CaptureParallelEnv(config), num_cycles=N_STEPS)


def test_spaces_and_sizes(pz_env):
    env = pz_env.capture_env
    assert pz_env.possible_agents == ["uav0", "uav1", "uav2", "uav3"]
    agent = pz_env.possible_agents[0]
    assert pz_env.observation_space(agent) is pz_env.observation_space(agent)
    assert pz_env.action_space(agent) is pz_env.action_space(agent)
    assert pz_env.action_space(agent) is not pz_env.action_space("uav1")   # seeded independently
    assert pz_env.action_space(agent).shape == (3,)
    obs, infos = pz_env.reset(seed=0)
    assert set(obs) == set(infos) == set(pz_env.agents) == set(pz_env.possible_agents)
    for a, o in obs.items():
        assert o.dtype == np.float32 and o.shape == (env.obs_size,)
        assert pz_env.observation_space(a).contains(o)
    assert pz_env.state_space.contains(pz_env.state())
    with pytest.raises(KeyError, match="not_a_uav"):
        pz_env.action_space("not_a_uav")


def test_infos_sum_to_rewards(pz_env):
    pz_env.reset(seed=1)
    _, rewards, terminations, truncations, infos = pz_env.step(zeros(pz_env))
    for a in pz_env.possible_agents:
        info = infos[a]
        assert np.isclose(sum(info["terms"].values()), rewards[a], rtol=1e-5, atol=1e-6)
        assert set(info["failures"]) >= {"uav_ground", "non_finite"}
        assert not terminations[a] and not truncations[a]
        assert info["episode_length"] == 1 and not info["timeout"] and not info["success"]
    assert pz_env.state().shape == (pz_env.capture_env.state_size,)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action_names_agent(pz_env, bad):
    pz_env.reset(seed=2)
    actions = zeros(pz_env)
    actions["uav2"] = np.array([0.0, bad, 0.0])
    with pytest.raises(ValueError, match=r"uav2.*non-finite"):
        pz_env.step(actions)


@pytest.mark.parametrize("shape", [(2,), (4,), (1, 3), ()])
def test_wrong_shape_names_agent(pz_env, shape):
    pz_env.reset(seed=2)
    actions = zeros(pz_env)
    actions["uav1"] = np.zeros(shape)
    with pytest.raises(ValueError, match=r"uav1.*shape"):
        pz_env.step(actions)


def test_missing_unknown_and_non_numeric_agents(pz_env):
    pz_env.reset(seed=2)
    actions = zeros(pz_env)
    del actions["uav3"]
    with pytest.raises(ValueError, match="uav3"):
        pz_env.step(actions)
    with pytest.raises(ValueError, match="uav9"):
        pz_env.step({**zeros(pz_env), "uav9": np.zeros(3)})
    with pytest.raises(ValueError, match="uav0.*numeric"):
        pz_env.step({**zeros(pz_env), "uav0": ["a", "b", "c"]})


def test_rejected_step_changes_nothing(pz_env):
    """A rejected action neither steps the physics nor advances the key."""
    clean = rollout(pz_env, 3, zeros(pz_env), 2)
    pz_env.reset(seed=3)
    bad = {**zeros(pz_env), "uav0": np.array([np.nan, 0.0, 0.0])}
    with pytest.raises(ValueError):
        pz_env.step(bad)
    again = [pz_env.step(zeros(pz_env))[0] for _ in range(2)]
    for a in pz_env.possible_agents:
        assert np.array_equal(clean[1][a], again[0][a]) and np.array_equal(clean[2][a], again[1][a])


def test_out_of_range_actions_are_clipped(pz_env):
    low = rollout(pz_env, 4, {a: np.array([1.0, -1.0, 1.0]) for a in pz_env.possible_agents}, 2)
    high = rollout(pz_env, 4, {a: np.array([5.0, -7.0, 1.5]) for a in pz_env.possible_agents}, 2)
    for a in pz_env.possible_agents:
        assert np.array_equal(low[-1][a], high[-1][a])


def test_episode_end_empties_agents(pz_env):
    pz_env.reset(seed=5)
    for i in range(N_STEPS):
        assert pz_env.agents == pz_env.possible_agents
        obs, rewards, terminations, truncations, infos = pz_env.step(zeros(pz_env))
        assert set(obs) == set(rewards) == set(truncations) == set(infos) == set(pz_env.possible_agents)
    assert all(truncations.values()) and not any(terminations.values())
    assert all(info["timeout"] and info["episode_length"] == N_STEPS for info in infos.values())
    assert pz_env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        pz_env.step({})
    pz_env.reset()
    assert pz_env.agents == pz_env.possible_agents


def test_same_seed_same_observations(pz_env, config):
    actions = {a: np.array([0.3, -0.2, 0.5]) for a in pz_env.possible_agents}
    first = rollout(pz_env, 11, actions, 3)
    second = rollout(pz_env, 11, actions, 3)
    other_env = CaptureParallelEnv(config)
    third = rollout(other_env, 11, actions, 3)
    for run in (second, third):
        for step_a, step_b in zip(first, run):
            for a in pz_env.possible_agents:
                assert step_a[a].tobytes() == step_b[a].tobytes()
    # a different seed spawns the target elsewhere
    other = rollout(pz_env, 12, actions, 0)
    assert not np.array_equal(first[0]["uav0"], other[0]["uav0"])


def test_bad_seed_and_render_mode(pz_env):
    with pytest.raises(ValueError, match="seed"):
        pz_env.reset(seed=-1)
    with pytest.raises(TypeError, match="seed"):
        pz_env.reset(seed=1.5)
    with pytest.raises(ValueError, match="render_mode"):
        CaptureParallelEnv.from_env(pz_env.capture_env, pz_env.env_params, render_mode="human")


def test_render(pz_env):
    pz_env.reset(seed=0)
    with pytest.warns(UserWarning, match="render"):
        assert pz_env.render() is None
    env = CaptureParallelEnv.from_env(pz_env.capture_env, pz_env.env_params, render_mode="rgb_array")
    env.reset(seed=0)
    image = env.render()
    env.close()
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert image.min() < image.max()
