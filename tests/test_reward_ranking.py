"""Rewards rank outcomes: on the default training file's environment at the scene's cheap
level ``train`` (where its profile ``scratch`` trains; the reward is computed by the same
code at every level), three teams (the
scripted team, a team hovering where it starts, and a team flying apart at full speed,
which the net's tethers tip over within a second) fly
the same numbered episodes, and every caught episode returns more than every missed one
(target on the ground, or time out), every missed one more than every crashed one
(mysim_jax/tasks/rewards.py; the bound that guarantees it is env_config.return_bounds)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.env import CRASHES, REWARD_TERMS, return_bounds

TRAIN_FILE = "configs/train_capture_falling.yaml"
EPISODES = 16


@pytest.mark.slow
def test_caught_beats_missed_beats_crashed_for_every_team():
    from mysim_jax.mappo.run import load_run_config, make_environment
    from mysim_jax.tasks.evaluate import Evaluator

    prepared = load_run_config(TRAIN_FILE, ["env.level=train"])
    assert prepared.scene.level == "train"
    env, params = make_environment(prepared)
    assert env.scene.quadrotor.setpoint_mode == "velocity"

    quads = np.asarray(env.quad_bodies)

    def team(key, obs, state, p, which):
        scripted = env.scripted_actions(state, p)
        hover = jnp.zeros_like(scripted)                                  # velocity 0: hold in place
        pos = state.sim.phys.body_pos[quads]
        outward = pos - jnp.mean(pos, axis=0)
        scatter = outward / (jnp.linalg.norm(outward, axis=1, keepdims=True) + 1e-6)  # full speed apart
        return jnp.where(which == 0, scripted, jnp.where(which == 1, hover, scatter))

    evaluator = Evaluator(env, params, team, batch=EPISODES)
    key = jax.random.PRNGKey(2024)
    runs = {name: evaluator(key, EPISODES, jnp.int32(i)) for i, name in enumerate(("scripted", "hover", "scatter"))}

    returns = {"caught": [], "missed": [], "crashed": []}
    for name, st in runs.items():
        crashed = np.any([st.failures[f] for f in CRASHES], axis=0)
        missed = ~st.success & ~crashed
        for label, mask in (("caught", st.success), ("missed", missed), ("crashed", crashed)):
            returns[label] += list(st.returns[mask])
    # every kind of ending happened, so the ordering below is not vacuous
    assert runs["scripted"].success.mean() > 0.8
    assert np.any([runs["scatter"].failures[f] for f in CRASHES], axis=0).all()
    assert len(returns["missed"]) >= 5, {k: len(v) for k, v in returns.items()}
    assert min(returns["caught"]) > max(returns["missed"])
    assert min(returns["missed"]) > max(returns["crashed"])
    # the guarantee behind it: the outcome weights exceed the bound on shaping and costs
    w = {k: float(v) for k, v in zip(REWARD_TERMS, params.weights)}
    bound = return_bounds(w, env.n_agents, env.max_steps, float(params.discount))["spread"]
    assert w["success"] > bound and w["crash"] > w["miss"] + bound

