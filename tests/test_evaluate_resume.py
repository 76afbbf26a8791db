"""An interrupted evaluation resumes from its checkpoint with exactly the numbers an
uninterrupted one gives (mysim_jax.tasks.evaluate.Checkpoint), and a checkpoint of something
else is not resumed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import load_config

from conftest import CONFIGS

# a 3 x 3 net on one-mass tethers, 0.4 s (10 policy steps of 0.04 s): compiles in seconds
SMALL = ["env={}", "net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target,uav0]"]
EPISODES, BATCH, CHUNK = 7, 3, 2


class Interrupted(RuntimeError):
    pass


@pytest.fixture(scope="module")
def evaluator():
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.evaluate import Evaluator, random_policy, scripted_policy

    env, params = make_env(load_config(CONFIGS / "capture_falling.yaml", SMALL))
    scripted, random = scripted_policy(env), random_policy(env)

    def either(k, obs, state, p, use_random):
        return jnp.where(use_random, random(k, obs, state, p), scripted(k, obs, state, p))

    ev = Evaluator(env, params, either, batch=BATCH, chunk=CHUNK)
    real = ev._advance(BATCH)
    calls = {"n": 0, "stop_at": None}

    def counted(*args):
        calls["n"] += 1
        if calls["stop_at"] is not None and calls["n"] >= calls["stop_at"]:
            raise Interrupted
        return real(*args)

    ev._compiled[BATCH] = counted
    return ev, calls


def _same(a, b):
    for name in ("success", "timeout", "length", "returns", "slot"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for group in ("failures", "terms"):
        for k in getattr(a, group):
            np.testing.assert_array_equal(getattr(a, group)[k], getattr(b, group)[k], err_msg=f"{group} {k}")


def test_an_interrupted_evaluation_resumes_to_the_same_numbers(evaluator, tmp_path):
    from mysim_jax.tasks.evaluate import Checkpoint

    ev, calls = evaluator
    key, use_random = jax.random.PRNGKey(11), jnp.bool_(True)
    calls.update(n=0, stop_at=None)
    whole = ev(key, EPISODES, use_random)
    full_calls = calls["n"]
    assert full_calls >= 6 and np.unique(whole.slot).size == BATCH      # several waves of episodes

    path = tmp_path / "resume" / "team.npz"
    check = Checkpoint(path, "falling, random team", every_s=0.0)      # saved after every call
    calls.update(n=0, stop_at=full_calls // 2 + 1)
    with pytest.raises(Interrupted):
        ev(key, EPISODES, use_random, checkpoint=check)
    assert path.exists() and not path.with_name(path.name + ".tmp").exists()
    with np.load(path) as z:
        ended = z["episodes"].size
    assert 0 < ended < EPISODES                                          # stopped halfway through

    calls.update(n=0, stop_at=None)
    resumed = ev(key, EPISODES, use_random, checkpoint=check)
    assert calls["n"] == full_calls - full_calls // 2                   # went on, did not start over
    _same(resumed, whole)
    assert resumed.policy_steps == whole.policy_steps
    assert resumed.extra["resumed_wall_s"] > 0

    # the finished file is read back whole: nothing is run again
    calls.update(n=0)
    _same(ev(key, EPISODES, use_random, checkpoint=check), whole)
    assert calls["n"] == 0


@pytest.mark.parametrize("change", ["fingerprint", "key", "episodes"])
def test_a_checkpoint_of_something_else_is_not_resumed(evaluator, tmp_path, change):
    from mysim_jax.tasks.evaluate import Checkpoint

    ev, calls = evaluator
    key, n, use = jax.random.PRNGKey(11), EPISODES, jnp.bool_(False)
    path = tmp_path / "team.npz"
    calls.update(n=0, stop_at=3)
    with pytest.raises(Interrupted):
        ev(key, n, use, checkpoint=Checkpoint(path, "scripted team", every_s=0.0))
    fingerprint = "scripted team"
    if change == "fingerprint":
        fingerprint = "another scene"
    elif change == "key":
        key = jax.random.PRNGKey(12)
    else:
        n = EPISODES - 1
    calls.update(n=0, stop_at=None)
    fresh = ev(key, n, use)
    started = calls["n"]
    calls.update(n=0)
    again = ev(key, n, use, checkpoint=Checkpoint(path, fingerprint, every_s=0.0))
    assert calls["n"] == started                                         # ran from the first episode
    _same(again, fresh)


def test_an_unreadable_checkpoint_is_run_from_the_start(evaluator, tmp_path):
    from mysim_jax.tasks.evaluate import Checkpoint

    ev, calls = evaluator
    path = tmp_path / "team.npz"
    path.write_bytes(b"not an npz file")
    calls.update(n=0, stop_at=None)
    stats = ev(jax.random.PRNGKey(2), 3, jnp.bool_(False), checkpoint=Checkpoint(path, "x", every_s=1e9))
    assert stats.n == 3 and calls["n"] > 0
    with np.load(path) as z:                                             # overwritten at the end
        assert z["episodes"].tolist() == [0, 1, 2]


def test_the_sweeps_fingerprint_follows_the_files(tmp_path):
    """A sweep's checkpoints name the teams' files and the package's source by digest
    (mysim_jax.tasks.grid.files_digest): a changed file is another digest."""
    from mysim_jax.tasks.evaluate import files_digest

    team = tmp_path / "policy"
    (team / "sub").mkdir(parents=True)
    (team / "a.msgpack").write_bytes(b"weights")
    (team / "sub" / "b.json").write_text("{}")
    first = files_digest(team)
    assert len(first) == 64 and files_digest(team) == first
    (team / "sub" / "b.json").write_text('{"x": 1}')
    assert files_digest(team) != first
    assert files_digest(team, ".py") == ""                    # no such files
    assert files_digest("scripted") == "" and files_digest(team / "a.msgpack") != files_digest(team)
