"""MAPPO: the loss pieces against hand calculations, learning on the builtin reach task,
determinism, and the training file's checks.

The hand calculations are plain Python loops over the textbook formulas (GAE: Schulman et
al. 2016, eq. 16; PPO: Schulman et al. 2017, eq. 7; MAPPO's clipped value loss: Yu et al.
2022), written apart from mysim_jax.mappo.losses.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.config import AlgoConfig, train_config_from_dict
from mysim_jax.mappo.losses import RunningStats, gae, gaussian_log_prob, policy_loss, value_loss
from mysim_jax.mappo.toy import ReachEnv
from mysim_jax.mappo.algorithm import make_train
from mysim_jax.mappo.trainer import Trainer


def test_gae_matches_a_hand_calculation():
    rng = np.random.default_rng(0)
    T, n = 7, 3
    r = rng.normal(size=(T, n))
    v = rng.normal(size=(T, n))
    d = rng.random((T, n)) < 0.3
    last = rng.normal(size=n)
    gamma, lam = 0.97, 0.9
    adv_ref = np.zeros((T, n))
    for j in range(n):
        a_next, v_next = 0.0, last[j]
        for t in reversed(range(T)):
            nonterminal = 0.0 if d[t, j] else 1.0
            delta = r[t, j] + gamma * v_next * nonterminal - v[t, j]
            a_next = delta + gamma * lam * nonterminal * a_next
            adv_ref[t, j] = a_next
            v_next = v[t, j]
    adv, ret = gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), jnp.asarray(last), gamma, lam)
    np.testing.assert_allclose(np.asarray(adv), adv_ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(ret), adv_ref + v, rtol=1e-5, atol=1e-5)


def test_gae_with_lambda_one_is_the_discounted_return():
    r = np.array([1.0, 2.0, 3.0, 4.0])
    v = np.zeros(4)
    d = np.array([False, True, False, False])
    adv, _ = gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), jnp.asarray(10.0), 0.5, 1.0)
    # episode 1: steps 0-1; episode 2 starts at step 2 and is bootstrapped with 10
    expected = [1 + 0.5 * 2, 2, 3 + 0.5 * 4 + 0.25 * 10, 4 + 0.5 * 10]
    np.testing.assert_allclose(np.asarray(adv), expected, rtol=1e-6)


def test_policy_loss_clips_the_ratio():
    adv = np.array([1.0, 1.0, -1.0, -1.0, 2.0])
    ratio = np.array([1.5, 0.7, 1.5, 0.7, 1.1])
    old = np.zeros(5)
    new = np.log(ratio)
    eps = 0.2
    hand = -np.mean([min(rt * a, min(max(rt, 1 - eps), 1 + eps) * a) for rt, a in zip(ratio, adv)])
    # by case: +A above 1+eps is capped (1.2), +A below 1-eps is not (0.7),
    # -A above 1+eps is not capped (-1.5), -A below 1-eps is (-0.8), inside: 2.2
    assert hand == pytest.approx(-(1.2 + 0.7 - 1.5 - 0.8 + 2.2) / 5)
    loss, clip_frac, kl = policy_loss(jnp.asarray(new), jnp.asarray(old), jnp.asarray(adv), eps)
    assert float(loss) == pytest.approx(hand, rel=1e-6)
    assert float(clip_frac) == pytest.approx(4 / 5)
    assert float(kl) == pytest.approx(np.mean((ratio - 1) - np.log(ratio)), rel=1e-5)


def test_value_loss_takes_the_larger_of_clipped_and_unclipped():
    v = np.array([1.0, 0.0, 2.0])
    old = np.array([0.0, 0.0, 1.9])
    target = np.array([1.0, 1.0, 0.0])
    eps = 0.2
    hand = 0.5 * np.mean([max((vi - ti) ** 2, (oi + min(max(vi - oi, -eps), eps) - ti) ** 2)
                          for vi, oi, ti in zip(v, old, target)])
    # first: unclipped 0, clipped (0.2 - 1)^2 = 0.64 -> 0.64; second: both 1; third: the
    # move (0.1) is inside the clip, both 4
    assert hand == pytest.approx(0.5 * (0.64 + 1 + 4) / 3)
    assert float(value_loss(jnp.asarray(v), jnp.asarray(old), jnp.asarray(target), eps)) == pytest.approx(hand)


def test_gaussian_log_prob():
    x, mean, log_std = np.array([0.3, -1.0]), np.array([0.0, 0.5]), np.array([math.log(0.5), 0.0])
    hand = sum(-0.5 * ((xi - mi) / math.exp(ls)) ** 2 - ls - 0.5 * math.log(2 * math.pi)
               for xi, mi, ls in zip(x, mean, log_std))
    assert float(gaussian_log_prob(jnp.asarray(x), jnp.asarray(mean), jnp.asarray(log_std))) == pytest.approx(hand)


def test_running_stats_equal_the_pooled_moments():
    rng = np.random.default_rng(1)
    parts = [rng.normal(3.0, 2.0, size=(n, 4)) for n in (5, 17, 40)]
    s = RunningStats.create((4,))
    for p in parts:
        s = s.update(jnp.asarray(p))
    pooled = np.concatenate(parts)
    # the prior count (1e-4 at mean 0, var 1) shifts the moments by ~1e-6
    np.testing.assert_allclose(np.asarray(s.mean), pooled.mean(0), rtol=1e-4)
    np.testing.assert_allclose(np.asarray(s.var), pooled.var(0), rtol=1e-4)


SMALL = dict(num_envs=32, num_steps=16, lr=3e-3, init_std=0.5)


def test_reach_step_is_step_env_then_the_reset_of_an_ended_episode():
    """The reach task has the capture environment's pair: ``step_env`` returns the state the
    step reached, ``step`` the same unless the episode ended, then a fresh one from the key
    (the same reward and flags either way; ``final_global_state`` the ended episode's)."""
    env = ReachEnv(max_steps=2)
    params = env.default_params()
    _, state = env.reset(jax.random.PRNGKey(0), params)
    actions = jnp.full(env.action_shape, 0.5)
    key = jax.random.PRNGKey(1)
    for t in range(2):
        obs, reset, reward, term, trunc, info = env.step(key, state, actions, params)
        obs_e, after, reward_e, term_e, trunc_e, info_e = env.step_env(key, state, actions, params)
        np.testing.assert_array_equal(reward, reward_e)
        assert bool(trunc) == bool(trunc_e) == (t == 1) and not bool(term) and not bool(term_e)
        np.testing.assert_array_equal(info["final_global_state"], env.global_state(after))
        np.testing.assert_array_equal(info_e["global_state"], info_e["final_global_state"])
        np.testing.assert_array_equal(obs_e, env.observe(after))
        if t == 0:      # not ended: the same step
            np.testing.assert_array_equal(reset.pos, after.pos)
            np.testing.assert_array_equal(obs, obs_e)
        else:           # ended: a fresh episode
            assert int(reset.steps) == 0 and int(after.steps) == 2
            np.testing.assert_array_equal(reset.goal, env.reset(key, params)[1].goal)
            np.testing.assert_array_equal(info["global_state"], env.global_state(reset))
        state = after


@functools.cache
def _reach_run(batching: str):
    """The reach task's 40-iteration run from key 0 with ``algo.batching`` ``batching``:
    ``(jitted train, final state, metrics)``, made once per batching for the tests below."""
    env = ReachEnv()
    cfg = AlgoConfig(total_env_steps=32 * 16 * 40, batching=batching, **SMALL)
    train = jax.jit(make_train(cfg, env, env.default_params()))
    state, hist = train(jax.random.PRNGKey(0))
    return train, state, hist


@pytest.mark.parametrize("batching", ["batch_last", "vmap"])
def test_learning_happens_on_the_reach_task_and_the_same_seed_gives_the_same_curve(batching):
    """40 iterations (20,480 team steps, a few seconds) as one compiled scan: the mean step
    reward rises by more than 0.25 from the first iterations to the last, and the success
    rate over the last 5 iterations from below 30 % to above 85 % (measured 0.88-0.99 over
    keys 0-5 under both XLA code generators). The same seed gives the same curve exactly;
    another seed another. Both ways of batching the environments (``algo.batching``) learn,
    and their first iterations agree to float32 round-off."""
    env = ReachEnv()
    train, state, hist = _reach_run(batching)
    reward, success = np.asarray(hist["step_reward"]), np.asarray(hist["success_rate"])
    assert reward.shape == success.shape == (40,)
    assert reward[-5:].mean() > reward[2:6].mean() + 0.25
    assert success[-5:].mean() > 0.85 and success[2:6].mean() < 0.3
    assert int(state.iteration) == 40
    assert state.obs.shape == (32, 2, env.obs_size)
    _, again = train(jax.random.PRNGKey(0))
    assert all(np.array_equal(hist[k], again[k]) for k in hist)
    _, other = train(jax.random.PRNGKey(1))
    assert not np.array_equal(hist["step_reward"], other["step_reward"])
    # the other batching: the first iterations agree to float32 round-off (later ones drift
    # apart, as any round-off does through PPO's updates; both learn, above)
    _, _, other_hist = _reach_run("vmap" if batching == "batch_last" else "batch_last")
    for k in hist:
        a, b = np.asarray(hist[k][:5], float), np.asarray(other_hist[k][:5], float)
        np.testing.assert_allclose(a, b, rtol=0, atol=3e-6 * max(1.0, float(np.max(np.abs(b)))), err_msg=k)


def test_the_batching_is_the_platform_s_unless_chosen():
    """``algo.batching: auto`` is batch-last on a CPU and ``jax.vmap`` on a GPU or TPU; a
    trainer on this (CPU) machine resolves it to batch-last; an unknown value is an error."""
    from mysim_jax.core.batching import resolve_batching

    assert [resolve_batching("auto", p) for p in ("cpu", "gpu", "tpu")] == ["batch_last", "vmap", "vmap"]
    assert resolve_batching("vmap", "cpu") == "vmap" and resolve_batching("batch_last", "gpu") == "batch_last"
    with pytest.raises(ValueError, match="batching must be auto, batch_last or vmap; got 'first'"):
        resolve_batching("first")
    env = ReachEnv()
    assert Trainer(AlgoConfig(**SMALL), env, env.default_params()).env_batching == "batch_last"
    assert Trainer(AlgoConfig(batching="vmap", **SMALL), env, env.default_params()).env_batching == "vmap"


def test_seeds_vmapped_in_one_program_equal_separate_runs():
    """``jax.vmap(train)`` over two keys trains both seeds in one program: each seed's
    parameters and curve equal its own separate run's to float32 round-off (vmap batches
    the matrix products differently, so not bit for bit), and the two seeds differ."""
    env = ReachEnv()
    cfg = AlgoConfig(total_env_steps=32 * 16 * 6, **SMALL)
    train = make_train(cfg, env, env.default_params())
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    both_state, both = jax.jit(jax.vmap(train))(keys)
    # each seed on its own, with the same train (the trainer's settings were first made
    # inside the vmapped trace: nothing of that trace may stay behind in them)
    one = jax.jit(train)
    worst = worst_m = 0.0
    for i in range(2):
        state, hist = one(keys[i])
        assert int(both_state.iteration[i]) == int(state.iteration) == 6
        for k in hist:
            a, b = np.asarray(both[k][i], float), np.asarray(hist[k], float)
            # relative to each metric's scale (losses, KL and returns differ by orders of magnitude)
            np.testing.assert_allclose(a, b, rtol=0, atol=3e-6 * max(1.0, float(np.max(np.abs(b)))), err_msg=k)
            worst_m = max(worst_m, float(np.max(np.abs(a - b))) / max(1.0, float(np.max(np.abs(b)))))
        got = jax.tree.map(lambda x: np.asarray(x[i]), both_state.params)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(state.params)):
            np.testing.assert_allclose(a, np.asarray(b), rtol=0, atol=2e-6)
            worst = max(worst, float(np.max(np.abs(a - np.asarray(b)))))
    assert not np.allclose(np.asarray(both["step_reward"][0]), np.asarray(both["step_reward"][1]))
    print(f"vmapped seeds vs separate runs: max |parameter difference| {worst:.3g}, metrics {worst_m:.3g} of scale")


def _raw(**algo):
    return {"name": "t", "env": {"builtin": "reach"}, "algo": algo}


@pytest.mark.parametrize("algo, field", [
    ({"num_envs": 10, "num_steps": 3, "num_minibatches": 4}, "num_minibatches"),
    ({"lr": 0.0}, "algo.lr"),
    ({"lr": -1e-3}, "algo.lr"),
    ({"learning_rate": 1e-3}, "learning_rate"),
    ({"num_envs": 64, "num_steps": 16, "total_env_steps": 100}, "total_env_steps"),
    ({"hidden": []}, "hidden"),
    ({"gamma": 1.5}, "algo.gamma"),
    ({"batching": "batch_first"}, "algo.batching"),
])
def test_bad_algo_settings_name_the_field(algo, field):
    with pytest.raises(ConfigError) as err:
        train_config_from_dict(_raw(**algo), "t.yaml")
    assert field in str(err.value)


def test_the_run_s_environments_shape_with_algo_gamma():
    """The run's environment takes the learner's discount as a parameter
    (``make_env(discount=algo.gamma)``) while its scene keeps its own ``env.discount``; a
    gamma under which the scene's outcomes no longer outweigh the shaping is refused,
    naming algo.gamma."""
    from mysim_jax.mappo.run import load_run_config, make_environment

    p = load_run_config("configs/train_capture_falling.yaml", ["algo.gamma=0.97", "env.level=train"])
    assert p.scene.env.discount == 0.99
    _, params = make_environment(p)
    assert params.discount.dtype == jnp.float32 and params.discount == np.float32(0.97)
    with pytest.raises(ConfigError, match=r"env.scene: with the learner's discount algo.gamma = 0.5 .*"
                                          r"env.rewards.success = .* must exceed"):
        load_run_config("configs/train_capture_falling.yaml", ["algo.gamma=0.5"])


def test_env_section_needs_exactly_one_source():
    with pytest.raises(ConfigError, match="exactly one of scene"):
        train_config_from_dict({"name": "t", "env": {}}, "t.yaml")
    with pytest.raises(ConfigError, match="exactly one of scene"):
        train_config_from_dict({"name": "t", "env": {"builtin": "reach", "scene": "x.yaml"}}, "t.yaml")
    with pytest.raises(ConfigError, match="unknown_section"):
        train_config_from_dict({"name": "t", "env": {"builtin": "reach"}, "unknown_section": {}}, "t.yaml")


def test_derived_sizes_are_computed():
    cfg = AlgoConfig(num_envs=64, num_steps=16, num_minibatches=8, update_epochs=3, total_env_steps=10_000)
    assert cfg.batch_size == 1024
    assert cfg.minibatch_size == 128
    assert cfg.num_iterations == 9
    assert cfg.num_updates == 9 * 3 * 8


def test_the_shipped_training_files_load():
    from conftest import CONFIGS

    from mysim_jax.mappo.config import load_train_config

    files = sorted(CONFIGS.glob("train_*.yaml"))
    assert files
    for path in files:
        cfg = load_train_config(path)
        assert cfg.algo.num_iterations >= 1, path.name
        for profile in cfg.profiles:
            assert load_train_config(path, profile=profile).profiles == cfg.profiles, (path.name, profile)


def test_a_profile_applies_its_overrides_before_the_command_line(tmp_path):
    """``--profile NAME`` applies the file's named overrides, then ``--set``; every profile
    is checked whichever runs; an unknown one names those the file has; the run folder's
    file is resolved (no profiles) and its description names the profile."""
    from mysim_jax.mappo.run_files import prepare, write_run_files

    raw = {"name": "t", "env": {"builtin": "reach"}, "algo": {"lr": 1e-3},
           "profiles": {"slow": ["algo.lr=1e-4", "run.seed=3", "name=t_slow"], "other": ["algo.num_envs=8"]}}
    plain = train_config_from_dict(raw, "t.yaml")
    assert plain.algo.lr == 1e-3 and plain.name == "t"
    slow = train_config_from_dict(raw, "t.yaml", profile="slow")
    assert (slow.algo.lr, slow.run.seed, slow.name, slow.algo.num_envs) == (1e-4, 3, "t_slow", 256)
    assert train_config_from_dict(raw, "t.yaml", ["algo.lr=5e-4"], "slow").algo.lr == 5e-4
    with pytest.raises(ConfigError, match=r"--profile fast: the file has no such profile \(it has: slow, other\)"):
        train_config_from_dict(raw, "t.yaml", profile="fast")
    broken = {**raw, "profiles": {**raw["profiles"], "bad": ["algo.lr=-1"]}}
    with pytest.raises(ConfigError, match=r"(?s)profile bad.*algo.lr: Input should be greater than 0"):
        train_config_from_dict(broken, "t.yaml", profile="slow")
    for profiles, match in (({"bad": "algo.lr=1"}, "profiles.bad: give a list"),
                            ({"bad": ["algo.lr"]}, "profiles.bad: --set 'algo.lr': expected key=value"),
                            (["algo.lr=1"], "profiles: give a mapping")):
        with pytest.raises(ConfigError, match=match):
            train_config_from_dict({**raw, "profiles": profiles}, "t.yaml")
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(raw))
    prepared = prepare(str(path), ["run.checkpoint_every=2"], str(tmp_path / "run"), profile="slow")
    write_run_files(prepared)
    written = yaml.safe_load((tmp_path / "run" / "train.yaml").read_text())
    assert written["profiles"] == {} and written["description"] == "(profile slow)"
    resolved = train_config_from_dict(written, "train.yaml")
    assert (resolved.algo.lr, resolved.run.seed, resolved.run.checkpoint_every) == (1e-4, 3, 2)


def test_residual_policy_adds_the_base_team_and_needs_one():
    """A residual policy's action is the base team's plus the actor's mean (clipped); the
    builtin task has no scripted team, so residual training on it is a config error."""
    from mysim_jax.mappo.networks import Actor, deterministic_policy

    actor = Actor(action_dim=2, hidden=(8,))
    obs = jnp.ones((2, 5))
    params = actor.init(jax.random.PRNGKey(0), obs[0])
    arrays = {"actor": params, "obs_mean": jnp.zeros(5), "obs_var": jnp.ones(5)}
    base = jnp.array([[0.5, -0.2], [0.95, -1.0]])
    plain = deterministic_policy(actor, arrays)(None, obs, None, None)
    residual = deterministic_policy(actor, arrays, base=lambda state, p: base)(None, obs, None, None)
    np.testing.assert_allclose(np.asarray(residual), np.clip(np.asarray(plain) + np.asarray(base), -1, 1), atol=1e-6)
    with pytest.raises(ConfigError, match="algo.residual"):
        train_config_from_dict({"name": "t", "env": {"builtin": "reach"}, "algo": {"residual": True}}, "t.yaml")


def test_target_kl_stops_the_epochs_and_the_critic_warm_up_holds_the_policy():
    """A tiny target KL stops an iteration's updates after its first minibatch (the KL of
    the unchanged policy is 0, of the updated one not); during the critic's warm-up the
    actor does not move while the critic does."""
    env = ReachEnv()
    params = env.default_params()
    key = jax.random.PRNGKey(0)
    # the KL limit is an argument of the compiled iteration: both trainers run one program
    # (and the anchored one below the next test's, which plans as many iterations)
    free = Trainer(AlgoConfig(total_env_steps=32 * 16 * 8, **SMALL), env, params)
    stopped = Trainer(AlgoConfig(total_env_steps=32 * 16 * 8, target_kl=1e-9, **SMALL), env, params)
    _, m_free = free.iteration(free.init(key))
    _, m_stop = stopped.iteration(stopped.init(key))
    assert float(m_free["updates_applied"]) == 1.0
    # 4 epochs x 4 minibatches: the first update is applied, the KL check stops the rest
    assert float(m_stop["updates_applied"]) == pytest.approx(1 / 16)

    warm = Trainer(AlgoConfig(total_env_steps=32 * 16 * 8, init="bc", **SMALL), env, params)
    assert warm.critic_warmup == 2
    ts0 = warm.init(key)
    ts1, m = warm.iteration(ts0)
    assert float(m["policy_coef"]) == 0.0
    for a, b in zip(jax.tree.leaves(ts1.params["actor"]), jax.tree.leaves(ts0.params["actor"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert any(not np.array_equal(np.asarray(a), np.asarray(b))
               for a, b in zip(jax.tree.leaves(ts1.params["critic"]), jax.tree.leaves(ts0.params["critic"])))
    # after the warm-up the policy trains, with the anchor at full weight, decaying linearly
    assert [float(x) for x in warm.schedule(2)] == [1.0, 1.0]
    assert float(warm.schedule(2 + warm.config.bc.anchor_iterations // 2)[1]) == pytest.approx(0.5)
    assert float(warm.schedule(2 + warm.config.bc.anchor_iterations)[1]) == 0.0


def test_a_time_limit_is_bootstrapped_or_ends_the_task():
    """With ``bootstrap_time_limit`` (the default) a step that reaches the time limit gets
    ``γ V(last state)`` added to its reward; without it that step's reward is the
    environment's alone. The rollouts are otherwise the same (same keys, same networks),
    so the rewards differ exactly on the truncated steps (there by the bootstrap, which is
    nonzero for an untrained critic; its value is not recomputed here)."""
    env = ReachEnv()
    params = env.default_params()
    cfg = dict(total_env_steps=32 * 32, num_envs=32, num_steps=32, lr=3e-3, init_std=0.5)
    boot = Trainer(AlgoConfig(**cfg), env, params)
    ends = Trainer(AlgoConfig(bootstrap_time_limit=False, **cfg), env, params)
    ts = boot.init(jax.random.PRNGKey(3))
    traj_b = boot._rollout(ts)[-1]
    traj_e = ends._rollout(ts)[-1]
    np.testing.assert_array_equal(np.asarray(traj_b.raw_obs), np.asarray(traj_e.raw_obs))
    diff = np.asarray(traj_b.reward) - np.asarray(traj_e.reward)            # (T, B, A)
    done = np.asarray(traj_b.done)                                          # (T, B)
    timed_out = done & ~np.asarray(traj_b.success)
    assert 0 < timed_out.sum() < timed_out.size
    assert np.all(diff[~timed_out] == 0.0)           # every other step: the same reward
    assert np.all(np.abs(diff[timed_out]) > 1e-6)    # a time-out: the bootstrap, nonzero


def test_a_frozen_observation_normalisation_keeps_the_held_actor_unchanged():
    """During the critic's warm-up the actor's weights are held; with
    ``bc.freeze_obs_norm`` its observation statistics are held too, so the policy (weights
    and normalisation) after an iteration is the one before it, bit for bit. Without it
    the rollout updates the statistics, and the same weights act differently."""
    env = ReachEnv()
    params = env.default_params()
    key = jax.random.PRNGKey(0)
    policies = {}
    for frozen in (False, True):
        cfg = AlgoConfig(total_env_steps=32 * 16 * 8, init="bc", bc={"freeze_obs_norm": frozen}, **SMALL)
        trainer = Trainer(cfg, env, params)
        ts0 = trainer.init(key)
        ts1, m = trainer.iteration(ts0)
        assert float(m["policy_coef"]) == 0.0
        policies[frozen] = (trainer.policy_arrays(ts0), trainer.policy_arrays(ts1))
    before, after = policies[True]
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    before, after = policies[False]
    assert not np.array_equal(np.asarray(before["obs_mean"]), np.asarray(after["obs_mean"]))


def test_the_anchor_pulls_the_policy_towards_the_clone():
    """With the anchor at a large weight the policy's mean stays closer to the anchor
    policy's than without it, over the same iterations from the same start."""
    env = ReachEnv()
    params = env.default_params()
    common = dict(total_env_steps=32 * 16 * 8, **SMALL)
    a_none = Trainer(AlgoConfig(init="bc", bc={"critic_warmup": 0, "anchor_coef": 0.0}, **common), env, params)
    a_big = Trainer(AlgoConfig(init="bc", bc={"critic_warmup": 0, "anchor_coef": 100.0}, **common), env, params)

    def drift(trainer):
        ts = trainer.init(jax.random.PRNGKey(0))
        for _ in range(6):
            ts, _ = trainer.iteration(ts)
        obs = ts.obs.reshape(-1, env.obs_size)
        mine = trainer.anchor_means(trainer.policy_arrays(ts), obs)
        anchor = trainer.anchor_means(ts.anchor, obs)
        return float(jnp.sqrt(jnp.mean((mine - anchor) ** 2)))

    free, held = drift(a_none), drift(a_big)
    assert free > 0.05 and held < 0.3 * free, (free, held)


def test_model_selection_keeps_the_best_policy():
    env = ReachEnv()
    trainer = Trainer(AlgoConfig(total_env_steps=32 * 16 * 4, **SMALL), env, env.default_params())
    ts = trainer.init(jax.random.PRNGKey(0))
    first = trainer.policy_arrays(ts)
    ts = trainer.keep_if_best(ts, 10, -3.0)
    assert int(ts.best_iteration) == 0
    ts, _ = trainer.iteration(ts)
    worse = trainer.keep_if_best(ts, 9, 100.0)              # fewer successes: not kept
    assert int(worse.best_iteration) == 0
    for a, b in zip(jax.tree.leaves(trainer.run_policy(worse)), jax.tree.leaves(first)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    tie = trainer.keep_if_best(ts, 10, -2.0)                # as many, better return: kept
    assert int(tie.best_iteration) == 1
    for a, b in zip(jax.tree.leaves(trainer.run_policy(tie)), jax.tree.leaves(trainer.policy_arrays(ts))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("algo, message", [
    ({"init": "bc", "residual": True}, "choose one"),
    ({"init": "bc"}, "algo.init: bc clones the scripted team"),
    ({"target_kl": 0.0}, "algo.target_kl"),
    ({"init_std": 0.0}, "algo.init_std"),
    ({"bc": {"holdout": 1.0}}, "algo.bc.holdout"),
])
def test_bad_bc_and_kl_settings_name_the_field(algo, message):
    with pytest.raises(ConfigError, match=message):
        train_config_from_dict(_raw(**algo), "t.yaml")


def test_restored_checkpoint_leaves_are_placed_as_the_fresh_states(tmp_path):
    """A leaf the fresh state holds uncommitted comes back uncommitted (so a resumed run
    calls the program a fresh start compiled), a committed one stays committed; values exact."""
    from mysim_jax.mappo.checkpoint import Checkpoints

    saved = {"w": jnp.arange(6.0).reshape(2, 3), "n": jnp.asarray(7, jnp.int32)}
    ckpt = Checkpoints(tmp_path / "ckpt")
    ckpt.save(3, saved)
    fresh = {"w": jnp.zeros((2, 3)), "n": jax.device_put(jnp.zeros((), jnp.int32), jax.devices()[0])}
    assert not fresh["w"].committed and fresh["n"].committed
    back = ckpt.restore(3, fresh)
    ckpt.close()
    assert not back["w"].committed and back["n"].committed
    np.testing.assert_array_equal(np.asarray(back["w"]), np.asarray(saved["w"]))
    assert int(back["n"]) == 7 and back["n"].dtype == jnp.int32


def test_network_memory_is_checked_against_what_the_machine_has():
    """The estimate is a lower bound that grows with the square of the layer widths; the
    check refuses, naming algo.hidden, only what exceeds the memory it is given."""
    from mysim_jax.core.config_base import ConfigError
    from mysim_jax.mappo.config import AlgoConfig, check_memory, network_memory_bytes

    small, wide = AlgoConfig(hidden=[128, 128]), AlgoConfig(hidden=[4096, 4096])
    # 2 networks x 4 copies (weights, gradients, 2 moments) x 4 bytes of 128 * 128 + 3 * 128
    # numbers, and 2 x 2 x 4 bytes of activations of a minibatch x 256 units
    assert network_memory_bytes(small) == 4 * 2 * (4 * (128 * 128 + 128 + 256) + 2 * small.minibatch_size * 256)
    assert network_memory_bytes(wide) > 100 * network_memory_bytes(small)     # 32x wider: 1024x the weights
    check_memory(small, "t.yaml", available=2**30)
    with pytest.raises(ConfigError, match=r"t.yaml: algo.hidden \[4096, 4096\] .* needs at least 0.6 GiB"):
        check_memory(wide, "t.yaml", available=2**28)


def test_the_run_memory_estimate_counts_the_rollout_and_states_the_trainer_holds():
    """The trainer's estimate (sizes only, nothing compiled) equals the bytes of the
    rollout's Transition buffers plus the advantages and targets computed from them
    (jax.eval_shape of the rollout, float32), and three environment states per
    environment; a total over the memory given is refused naming every part and the
    fields of the largest."""
    from mysim_jax.core import batching
    from mysim_jax.mappo.config import check_memory_needs

    env = ReachEnv()
    cfg = AlgoConfig(num_envs=24, num_steps=5, num_minibatches=2, total_env_steps=24 * 5)
    trainer = Trainer(cfg, env, env.default_params())
    needs = trainer.memory_needs()
    ts = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    traj = jax.eval_shape(trainer._rollout, ts)[-1]
    advantage_and_target = 2 * 4 * cfg.num_envs * cfg.num_steps * env.n_agents
    assert needs["rollout buffers"] == (batching.tree_nbytes(traj) + advantage_and_target,
                                        "algo.num_envs x algo.num_steps")
    assert needs["environment states"] == (3 * batching.tree_nbytes(ts.env_state), "algo.num_envs")
    total = sum(b for b, _ in needs.values())
    check_memory_needs(needs, "t.yaml", available=total)
    with pytest.raises(ConfigError, match=r"^t.yaml: the run needs about .* \(networks .* \(algo.hidden\), .*\); "
                                          r"this machine has .* available: lower algo.hidden$"):
        check_memory_needs(needs, "t.yaml", available=total - 1)
