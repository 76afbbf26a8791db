"""SHAC (``algo.name: shac``, mysim_jax/mappo/shac.py) on the built-in reach task: the
actor's gradient through the environment against finite differences, learning, and the
settings it refuses. Its runs on the capture tasks are in docs/shac.md."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.algorithm import make_train
from mysim_jax.mappo.config import AlgoConfig, train_config_from_dict
from mysim_jax.mappo.shac import ShacTrainer, make_trainer
from mysim_jax.mappo.toy import ReachEnv
from mysim_jax.mappo.trainer import Trainer

SHAC = dict(name="shac", num_envs=32, num_steps=8, num_minibatches=4, lr=2e-3, lr_schedule="constant",
            init_std=0.3, max_grad_norm=1.0, shac={"critic_lr": 1e-3})


def test_the_actor_s_gradient_through_the_environment_matches_finite_differences():
    """The gradient of the actor's loss (a 4-step horizon of 8 reach environments, through
    every step of the environment, the critic's bootstrap and the episodes that end inside
    the horizon) along a random direction of the actor's parameters, against central
    differences of the same loss (float32, step 1e-3): measured relative error 3.4e-5."""
    env = ReachEnv()
    cfg = AlgoConfig(**{**SHAC, "num_envs": 8, "num_steps": 4, "num_minibatches": 1})
    trainer = make_trainer(cfg, env, env.default_params())
    assert isinstance(trainer, ShacTrainer)
    ts = trainer.init(jax.random.PRNGKey(3))

    def loss(actor):
        return trainer._actor_loss(actor, ts, 1.0, 0.0)[0]

    actor = ts.params["actor"]
    grad = jax.jit(jax.grad(loss))(actor)
    leaves, tree = jax.tree.flatten(actor)
    keys = jax.random.split(jax.random.PRNGKey(4), len(leaves))
    direction = tree.unflatten([jax.random.normal(k, x.shape, x.dtype) for k, x in zip(keys, leaves)])
    along = sum(float(jnp.vdot(g, d)) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))
    f = jax.jit(lambda s: loss(jax.tree.map(lambda a, d: a + s * d, actor, direction)))
    eps = 1e-3
    fd = (float(f(eps)) - float(f(-eps))) / (2 * eps)
    assert abs(along) > 1e-3                       # the loss depends on the actor through the environment
    assert abs(fd - along) <= 3.5e-4 * abs(along), (fd, along)


def test_gradient_windows_cut_the_gradient_between_them():
    """``shac.horizon`` 1 over a rollout of 4 steps: the actor's loss and its gradient are
    the mean of four one-step losses flown one after the other from where the last ended
    (the same keys): measured equal values and gradients equal to 1.1e-7 of the largest
    component; nothing crosses a window's start. The same rollout as one window has
    another gradient (measured: it differs by 1.03 of the largest component)."""
    env = ReachEnv()
    base = {**SHAC, "num_envs": 8, "num_minibatches": 1}
    windows = make_trainer(AlgoConfig(**{**base, "num_steps": 4, "shac": {"horizon": 1}}), env, env.default_params())
    whole = make_trainer(AlgoConfig(**{**base, "num_steps": 4}), env, env.default_params())
    single = make_trainer(AlgoConfig(**{**base, "num_steps": 1}), env, env.default_params())
    ts = single.init(jax.random.PRNGKey(5))
    actor = ts.params["actor"]
    grad_of = jax.jit(jax.value_and_grad(lambda a, t, tr: tr._actor_loss(a, t, 1.0, 0.0)[0]), static_argnums=2)
    value, grad = grad_of(actor, ts, windows)
    _, grad_whole = grad_of(actor, ts, whole)
    values, grads, t = [], [], ts
    for _ in range(4):
        v, g = grad_of(actor, t, single)
        env_state, obs, gstate, key = single._actor_loss(actor, t, 1.0, 0.0)[1][1]
        t = t.replace(env_state=env_state, obs=obs, global_state=gstate, key=key)
        values.append(float(v))
        grads.append(g)
    mean_grad = jax.tree.map(lambda *g: sum(g) / 4.0, *grads)
    np.testing.assert_allclose(float(value), np.mean(values), rtol=1e-6)
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])
    scale = np.max(np.abs(flat(mean_grad)))
    np.testing.assert_allclose(flat(grad), flat(mean_grad), rtol=0, atol=1e-6 * scale)
    assert np.max(np.abs(flat(grad_whole) - flat(mean_grad))) > 0.1 * scale


def test_shac_learns_the_reach_task_and_the_same_seed_gives_the_same_curve():
    """60 iterations of 32 environments x 8 steps (15,360 team steps; PPO's test in
    tests/test_mappo.py runs 20,480) as one compiled scan: the success rate over the last
    5 iterations rises from below 30 % to above 90 % (measured 0.99-1.00 with keys 0-5),
    every actor gradient is finite and applied, and the same key gives the same curve
    exactly."""
    env = ReachEnv()
    cfg = AlgoConfig(**SHAC, total_env_steps=32 * 8 * 60)
    train = jax.jit(make_train(cfg, env, env.default_params()))
    state, hist = train(jax.random.PRNGKey(0))
    success = np.asarray(hist["success_rate"])
    assert success[2:6].mean() < 0.3 and success[-5:].mean() > 0.9, success
    assert np.all(np.asarray(hist["updates_applied"]) == 1.0)
    assert int(state.iteration) == 60
    assert set(state.opt_state) == {"actor", "critic"}
    _, again = train(jax.random.PRNGKey(0))
    assert all(np.array_equal(hist[k], again[k]) for k in hist)


def test_ppo_is_the_default_trainer():
    env = ReachEnv()
    trainer = make_trainer(AlgoConfig(), env, env.default_params())
    assert type(trainer) is Trainer


def test_the_memory_estimate_counts_what_the_backward_pass_keeps():
    """A SHAC trainer's estimate adds, to PPO's parts, the residuals reverse mode saves
    over the rollout (from jax.eval_shape of the actor loss's vjp): at least the actor's two
    hidden layers per step, environment and agent, growing with the environments and the
    steps; a machine that holds PPO's parts but not these refuses the run."""
    from mysim_jax.mappo.config import check_memory_needs

    env = ReachEnv()
    base = {**SHAC, "num_envs": 16, "num_steps": 4, "num_minibatches": 1}

    def needs(**change):
        return make_trainer(AlgoConfig(**{**base, **change}), env, env.default_params()).memory_needs()

    one = needs()
    ppo = Trainer(AlgoConfig(**base), env, env.default_params()).memory_needs()      # PPO's count of the same sizes
    assert {k: v for k, v in one.items() if k != "backward pass"} == ppo
    saved, fields = one["backward pass"]
    assert fields == "algo.num_envs x algo.num_steps"
    assert saved >= 2 * 4 * base["num_envs"] * base["num_steps"] * env.n_agents * 128
    assert needs(num_envs=32)["backward pass"][0] > 1.5 * saved
    assert needs(num_steps=8)["backward pass"][0] > 1.5 * saved
    ppo_total = sum(b for b, _ in ppo.values())
    check_memory_needs(ppo, "t.yaml", available=ppo_total)
    with pytest.raises(ConfigError, match=r"backward pass .* \(algo.num_envs x algo.num_steps\)"):
        check_memory_needs(one, "t.yaml", available=ppo_total)


@pytest.mark.parametrize("algo, words", [
    ({"name": "shac", "target_kl": 0.02}, "target_kl"),
    ({"name": "shac", "clip_eps": 0.1}, "clip_eps"),
    ({"name": "shac", "ent_coef": 0.01}, "ent_coef"),
    ({"shac": {"critic_lr": 1e-3}}, "algo.name is ppo"),
    ({"name": "shac", "shac": {"critic_lr": -1.0}}, "critic_lr"),
    ({"name": "sac"}, "algo.name"),
    ({"name": "shac", "num_steps": 8, "shac": {"horizon": 3}}, "shac.horizon 3 does not divide"),
])
def test_bad_shac_settings_are_refused_with_the_field(algo, words):
    with pytest.raises(ConfigError) as err:
        train_config_from_dict({"name": "t", "env": {"builtin": "reach"}, "algo": algo}, "t.yaml")
    assert words in str(err.value)


def test_scripts_train_runs_shac_and_writes_what_a_ppo_run_writes(tmp_path, capsys):
    """``scripts/train.py`` with ``algo.name: shac`` on the reach task (60 iterations of 32
    x 8 team steps, in this process): the run folder of a PPO run (metrics, policy, final
    evaluation, summary), a saved policy that catches what training learned (evaluation
    success above 90 %), and the PPO-only columns of metrics.csv
    left empty rather than filled with numbers SHAC does not have."""
    import csv
    import json

    from conftest import run_script_main
    from mysim_jax.mappo.config import reach_training_text

    cfg = tmp_path / "reach_shac.yaml"
    text = reach_training_text("reach_shac", 32 * 8 * 60, checkpoint_every=20, eval_episodes=200)
    cfg.write_text(text)
    sets = [f"algo.{k}={v}" for k, v in SHAC.items() if k != "shac"]
    sets.append(f"algo.shac.critic_lr={SHAC['shac']['critic_lr']}")
    out = tmp_path / "run"
    code, _, err, _ = run_script_main("train", [cfg, "--out", out, "--no-progress", "--set", *sets], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 60 and summary["stopped_by"] == "step_budget"
    assert summary["evaluation"]["success"]["rate"] > 0.9
    assert (out / "policy" / "policy.json").is_file()
    with (out / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 60 and rows[-1]["approx_kl"] == "" and float(rows[-1]["grad_norm"]) > 0
