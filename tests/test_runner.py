"""The episode runner (mysim_jax/tasks/runner.py) on the reach task: the policy's and the
environment's keys are those the hand-written loops it replaced drew, so the reach task's
evaluation and a keyed rollout give the same numbers bit for bit; ``first_done`` judges
the first episode; the hooks carry a caller's state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.mappo.run import evaluate_builtin
from mysim_jax.mappo.toy import ReachEnv
from mysim_jax.tasks.runner import first_done, numbered_keys, episode_keys, rollout, run_batch, shared_key, split_keys

ENV = ReachEnv()
PARAMS = ENV.default_params()


def _noisy(key, obs, state, params):
    """Towards the landmark, with noise the policy's key draws."""
    toward = jnp.clip((state.goal - state.pos) / (params.speed * ENV.dt), -1.0, 1.0)
    return 0.7 * toward + 0.8 * jax.random.normal(key, toward.shape)


def _old_evaluate_builtin(policy, episodes: int, seed: int) -> int:
    """The reach task's evaluation as it was written before the runner (one step key to
    both, success latched until the first ``done``)."""
    def one_episode(key):
        k0, k1 = jax.random.split(key)
        obs, state = ENV.reset(k0, PARAMS)

        def body(carry, k):
            obs, state, finished, success = carry
            a = policy(k, obs, state, PARAMS)
            obs, state, _, _, _, info = ENV.step(k, state, a, PARAMS)
            success = success | (info["success"] & ~finished)
            return (obs, state, finished | info["done"], success), None

        (_, _, _, success), _ = jax.lax.scan(body, (obs, state, jnp.bool_(False), jnp.bool_(False)),
                                             jax.random.split(k1, ENV.max_steps))
        return success

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    return int(jax.jit(jax.vmap(one_episode))(keys).sum())


def test_the_reach_evaluation_counts_what_the_hand_written_loop_counted():
    result = evaluate_builtin(ENV, PARAMS, _noisy, 64, 3)
    count = result["success"]["count"]
    assert count == _old_evaluate_builtin(_noisy, 64, 3)
    assert 0 < count < 64                       # the noise makes some episodes fail: the count can differ
    assert result["episodes"] == 64 and result["success"]["rate"] == count / 64
    # the library's batch-last vmap (run_batch's default) flies the same episodes
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    _, rows = run_batch(ENV, PARAMS, _noisy, keys, ENV.max_steps, step_keys=shared_key,
                        record=lambda step, aux: {"success": step.info["success"], "done": step.info["done"]})
    assert rows["done"].shape == (64, ENV.max_steps)
    outcome, ended = jax.vmap(first_done)(rows)
    assert int(np.sum(np.asarray(outcome["success"] & ended))) == count


def test_a_rollout_draws_the_keys_of_a_hand_written_scan():
    key = jax.random.PRNGKey(7)
    obs, state = ENV.reset(jax.random.PRNGKey(1), PARAMS)
    xs = jax.random.split(key, 40)              # longer than an episode: auto-resets inside

    def by_hand(obs, state):
        def body(carry, k):
            obs, state = carry
            k_act, k_step = jax.random.split(k)
            a = _noisy(k_act, obs, state, PARAMS)
            obs, state, reward, _, _, info = ENV.step(k_step, state, a, PARAMS)
            return (obs, state), (reward, info["done"])
        return jax.lax.scan(body, (obs, state), xs)

    def by_runner(obs, state):
        (obs, state, _), rows = rollout(ENV, PARAMS, _noisy, obs, state, xs,
                                        record=lambda step, aux: (step.reward, step.info["done"]))
        return (obs, state), rows

    want, got = jax.jit(by_hand)(obs, state), jax.jit(by_runner)(obs, state)
    for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(np.sum(got[1][1])) >= 1          # an episode ended and reset within the 40 steps


def test_numbered_keys_are_the_evaluations_and_the_hooks_carry_state():
    key = jax.random.PRNGKey(2)
    keys = numbered_keys(key, 5)
    for t in (0, 3):
        np.testing.assert_array_equal(np.asarray(keys(jnp.int32(t))), np.asarray(episode_keys(key, 5, t)[1:]))
    obs, state = ENV.reset(episode_keys(key, 5, 0)[0], PARAMS)

    def count(step, steps):              # the aux counts steps; the episode is held at its terminal state
        return step.next_obs, step.next_state, steps + 1

    (_, last, steps), rows = jax.jit(lambda o, s: rollout(
        ENV, PARAMS, _noisy, o, s, jnp.arange(ENV.max_steps), keys=keys, update=count, aux=jnp.int32(0),
        record=lambda step, aux: {"done": step.info["done"], "t": aux}, auto_reset=False))(obs, state)
    assert int(steps) == ENV.max_steps
    np.testing.assert_array_equal(np.asarray(rows["t"]), np.arange(ENV.max_steps))   # record sees the aux before
    assert int(last.steps) == ENV.max_steps                                          # never reset
    row, ended = first_done(rows)
    assert bool(ended) and int(row["t"]) == int(np.argmax(np.asarray(rows["done"])))


def test_first_done_of_rows_without_an_end_and_a_bad_length():
    row, ended = first_done({"done": jnp.zeros(4, bool), "x": jnp.arange(4)})
    assert not bool(ended) and int(row["x"]) == 0
    with pytest.raises(ValueError, match="length must be at least 1"):
        run_batch(ENV, PARAMS, _noisy, jax.random.split(jax.random.PRNGKey(0), 2), 0, step_keys=split_keys)
