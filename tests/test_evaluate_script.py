"""scripts/evaluate.py end to end on a small capture scene, its input checks, and
mysim_jax.tasks.episode.record_episode (the recorded episode ends at the pre-reset state)."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.config.scene import load_config
from mysim_jax.io.trajectory import read_trajectory_csv
from mysim_jax.config.env import FAILURES, REWARD_TERMS

from conftest import CONFIGS, ROOT, only_array_ops, run_script_main

SCRIPT = ROOT / "scripts" / "evaluate.py"
CONFIG = CONFIGS / "capture_falling.yaml"
# a 3 x 3 net on one-mass tethers, 0.4 s (10 policy steps of 0.04 s): compiles in seconds
SMALL = ["net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target,uav0]"]


def _small_sets() -> list[str]:
    return [a for s in SMALL for a in ("--set", s)]


def _run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args), *_small_sets(), "--no-progress"],
                          capture_output=True, text=True, cwd=ROOT)


def test_outputs_and_consistent_metrics(tmp_path):
    out = tmp_path / "eval"
    res = _run(CONFIG, "--policy", "scripted", "--episodes", 4, "--batch", 2, "--seed", 3, "--out", out,
               "--no-animation", "--compare", "random")
    assert res.returncode == 0, res.stderr
    # the random team flew the same four episodes: a paired comparison
    comparison = json.loads((out / "comparison.json").read_text())
    assert (comparison["policy"], comparison["compare"], comparison["episodes"]) == ("scripted", "random", 4)
    assert comparison["both"] + comparison["neither"] + comparison["only_policy"] + comparison["only_compare"] == 4
    assert "on the same 4 episodes" in res.stdout
    assert len((out / "comparison_episodes.csv").read_text().splitlines()) == 5
    assert "no env: block" in res.stderr          # capture_falling.yaml has none: defaults, with a note
    for name in ("metrics.json", "episodes.csv", "outcomes.png", "reward_terms.png", "lengths.png", "returns.png",
                 "trajectory.csv", "config.yaml", "capture_top.png", "capture_side.png", "episode_steps.csv",
                 "episode_rewards.png"):
        assert (out / name).stat().st_size > 0, name
    assert not (out / "capture.gif").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["policy"], metrics["episodes"], metrics["batch"], metrics["seed"]) == ("scripted", 4, 2, 3)
    assert metrics["scene"] == "capture_falling" and metrics["env_block"] == "defaults"

    rows = read_trajectory_csv(out / "episodes.csv")
    np.testing.assert_array_equal(rows["episode"], np.arange(4))          # numbered, in order
    assert set(rows["slot"].astype(int)) == {0, 1}                        # both slots ran episodes
    flags = {"success": rows["success"], "timeout": rows["timeout"],
             **{f: rows[f"failure_{f}"] for f in FAILURES}}
    rates = {"success": metrics["success"], "timeout": metrics["timeout"], **metrics["failures"]}
    for name, flag in flags.items():
        r = rates[name]
        assert r["count"] == int(flag.sum()) and r["rate"] == pytest.approx(flag.mean()), name
        lo, hi = r["interval95"]
        assert 0.0 <= lo <= r["rate"] <= hi <= 1.0, name
    # an episode ends one way: success, or a failure, or the time limit
    assert np.all(rows["success"] + rows["timeout"] + (sum(rows[f"failure_{f}"] for f in FAILURES) > 0) == 1)
    assert metrics["mean_return"] == pytest.approx(rows["return"].mean(), rel=1e-6)
    assert metrics["mean_length_steps"] == pytest.approx(rows["length_steps"].mean())
    for t in REWARD_TERMS:
        assert metrics["mean_terms"][t] == pytest.approx(rows[f"term_{t}"].mean(), rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(sum(rows[f"term_{t}"] for t in REWARD_TERMS), rows["return"], rtol=1e-4)

    # the recorded episode (episode 0) in simulate.py's format, on the policy-step grid
    traj = read_trajectory_csv(out / "trajectory.csv")
    assert {"time", "target_x", "uav0_qw", "uav0_az", "uav0_rotor4", "net_k1_1_vz"} <= set(traj)
    rec = metrics["recorded_episode"]
    first = 0
    assert len(traj["time"]) == rec["length_steps"] + 1 == int(rows["length_steps"][first]) + 1
    np.testing.assert_allclose(traj["time"], np.arange(len(traj["time"])) * metrics["policy_dt"], atol=1e-5)
    # the replay is another compiled program: its rounding differs, and contact grows it
    # (mysim_jax/tasks/episode.py); measured 1.0e-3 relative with the code generator the
    # suite compiles with (tests/conftest.py), below 1e-3 with XLA's default one
    assert rec["mean_return"] == pytest.approx(rows["return"][first], rel=1e-2)
    assert {"caught", "min_uav_target_distance_m"} <= set(rec["capture"])


@pytest.mark.parametrize("case", ["missing_config", "missing_policy", "no_make_policy", "zero_episodes",
                                  "bad_override"])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, case):
    """The script's main() in this process (conftest.run_script_main): exit code 2, one
    error, nothing of the evaluation compiled (conftest.only_array_ops), nothing written."""
    out = tmp_path / "eval"
    no_function = tmp_path / "policy.py"
    no_function.write_text("def something_else(env, params):\n    return None\n")
    args = {
        "missing_config": (tmp_path / "nope.yaml", "--policy", "scripted", "--episodes", 2),
        "missing_policy": (CONFIG, "--policy", tmp_path / "nope.py", "--episodes", 2),
        "no_make_policy": (CONFIG, "--policy", no_function, "--episodes", 2),
        "zero_episodes": (CONFIG, "--policy", "scripted", "--episodes", 0),
        "bad_override": (CONFIG, "--policy", "scripted", "--episodes", 2, "--set", "env.policy_rate=7"),
    }[case]
    message = {"missing_config": "no such config file", "missing_policy": "no such file",
               "no_make_policy": "make_policy", "zero_episodes": "--episodes 0", "bad_override": "policy_rate"}[case]
    code, _, err, compiled = run_script_main("evaluate", [*args, "--out", out, *_small_sets(), "--no-progress"],
                                             capsys)
    assert code == 2, err
    assert err.startswith("error:") and message in err, err
    assert "Traceback" not in err and only_array_ops(compiled)
    assert not out.exists() and not list(tmp_path.glob(".eval*"))


def test_a_batch_larger_than_the_episodes_is_said(tmp_path, capsys):
    """Not an error (the batch becomes the episode count), but announced in one line; the
    missing scene then ends the run before anything loads."""
    code, _, err, _ = run_script_main("evaluate", [tmp_path / "nope.yaml", "--policy", "scripted", "--episodes", 2,
                                                   "--batch", 64, "--out", tmp_path / "o", *_small_sets()], capsys)
    assert code == 2
    assert "note: --batch 64 is more than --episodes 2: running 2 side by side" in err
    assert "no such config file" in err and "Traceback" not in err


def test_record_episode_stops_at_the_pre_reset_state():
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.episode import record_episode
    from mysim_jax.tasks.evaluate import random_policy

    # random setpoints and a UAV dipping 1 cm fails the episode: it ends on a failure, before the time limit
    config = load_config(CONFIG, ["env.failure.min_altitude=3.89", *SMALL])
    env, params = make_env(config)
    policy = random_policy(env)
    key = jax.random.PRNGKey(3)
    rec = record_episode(env, params, policy, key)
    assert 1 <= rec.length < env.max_steps and rec.outcome == "uav_altitude" and not rec.timeout
    t = rec.trajectory.time
    assert len(t) == rec.length + 1 and rec.rewards.shape == (rec.length, env.n_agents)
    # the last row is the terminal state, not the next episode's reset (which is at t = 0)
    np.testing.assert_allclose(t, np.arange(rec.length + 1) * env.policy_dt, atol=1e-5)
    assert np.isfinite(rec.trajectory.acc.body_acc).all()

    # the same episode stepped with env.step: same rewards, same states, and its state after
    # the last step is already the reset one
    from mysim_jax.tasks.evaluate import episode_keys

    k_reset, _, _ = episode_keys(key, 0, 0)
    obs, state = jax.jit(env.reset)(k_reset, params)
    step, act = jax.jit(env.step), jax.jit(policy)
    for i in range(rec.length):
        _, k_act, k_step = episode_keys(key, 0, i)
        obs, state, reward, _, _, info = step(k_step, state, act(k_act, obs, state, params), params)
        np.testing.assert_allclose(reward, rec.rewards[i], rtol=1e-4, atol=1e-5)
        if i < rec.length - 1:
            np.testing.assert_allclose(state.sim.phys.body_pos, rec.trajectory.phys.body_pos[i + 1], atol=1e-5)
    assert bool(info["done"]) and bool(info["failures"]["uav_altitude"])
    np.testing.assert_allclose(info["episode_return"], rec.returns, rtol=1e-4)
    assert float(state.sim.time) == 0.0 and int(state.steps) == 0


def test_policy_files_are_checked_before_compiling(tmp_path):
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.mappo.policies import PolicyError, check_policy, policy_maker

    env, params = make_env(load_config(CONFIG, ["env={}", *SMALL]))
    good = tmp_path / "hold.py"
    good.write_text("import jax.numpy as jnp\n\n"
                    "def make_policy(env, params):\n"
                    "    return lambda key, obs, state, params: jnp.zeros(env.action_shape, obs.dtype)\n")
    check_policy(env, params, policy_maker(str(good))(env, params), str(good))
    wrong = tmp_path / "wrong.py"
    wrong.write_text("import jax.numpy as jnp\n\n"
                     "def make_policy(env, params):\n"
                     "    return lambda key, obs, state, params: jnp.zeros((env.n_agents, 2))\n")
    with pytest.raises(PolicyError, match=r"shape \(4, 2\).*expected a real \(float\) array of shape \(4, 3\)"):
        check_policy(env, params, policy_maker(str(wrong))(env, params), str(wrong))
    broken = tmp_path / "broken.py"
    broken.write_text("def make_policy(env, params):\n    return 1 +\n")
    with pytest.raises(PolicyError, match="importing it failed: SyntaxError"):
        policy_maker(str(broken))
    checkpoint = tmp_path / "policy.ckpt"
    checkpoint.write_text("")
    with pytest.raises(PolicyError, match="not a Python file"):
        policy_maker(str(checkpoint))


def test_numbered_episodes_are_the_same_whatever_the_batch_and_the_team():
    """Episode i is drawn from its own key: batches of 2 and 3 slots run the same six
    episodes (their returns agree to 2e-3: the compiled programs differ and contact
    amplifies float32 rounding), and two teams get the same first state in every episode
    (the paired comparison relies on it). One program per batch size flies both teams (the
    argument picks the team), as the final evaluation of a training run does. (Batch 2 is
    the program test_outputs_and_consistent_metrics's evaluate.py run compiled: the
    persistent compilation cache serves it when that test ran first.)"""
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.evaluate import Evaluator, episode_keys, random_policy, scripted_policy
    from mysim_jax.tasks.report import compare

    env, params = make_env(load_config(CONFIG, ["env={}", *SMALL]))
    scripted, random = scripted_policy(env), random_policy(env)

    def either(k, obs, state, p, use_random):
        return jnp.where(use_random, random(k, obs, state, p), scripted(k, obs, state, p))

    key = jax.random.PRNGKey(5)
    by_batch = {b: Evaluator(env, params, either, batch=b) for b in (2, 3)}
    runs = [by_batch[b](key, 6, jnp.bool_(False)) for b in (2, 3)]
    np.testing.assert_array_equal(runs[1].length, runs[0].length)
    np.testing.assert_array_equal(runs[1].success, runs[0].success)
    np.testing.assert_allclose(runs[1].returns, runs[0].returns, rtol=0, atol=2e-3)   # measured 2e-4
    assert np.unique(runs[1].slot).size == 3                                          # slots were reused
    reset = jax.jit(env.reset)
    starts = [reset(episode_keys(key, i, 0)[0], params)[1] for i in range(6)]
    spawns = np.array([np.asarray(s.sim.phys.body_pos[env.target_body]) for s in starts])
    assert len({tuple(np.round(x, 6)) for x in spawns}) == 6               # six different episodes
    random_run = by_batch[3](key, 6, jnp.bool_(True))
    result = compare(runs[0], random_run, ("scripted", "random"))
    assert result["episodes"] == 6 and result["teams"] == ["scripted", "random"]
    assert result["both"] + result["neither"] + result["only_scripted"] + result["only_random"] == 6
    lo, hi = result["difference"]["interval95"]
    assert lo <= result["difference"]["estimate"] <= hi
    with pytest.raises(ValueError, match="same episodes"):
        compare(runs[0], by_batch[3](key, 3, jnp.bool_(True)))
    with pytest.raises(ValueError, match="at least 1"):
        Evaluator(env, params, lambda *a: None, batch=0)


@pytest.mark.float64
def test_a_float64_scene_is_evaluated_in_float64():
    """The slots' sums of reward terms take the scene's precision, so a float64 scene runs
    (it failed on a float32 carry) and its returns are the sums of its terms."""
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.evaluate import Evaluator, scripted_policy

    sets = [s for s in SMALL if not s.startswith("sim.precision")] + ["sim.precision=float64"]
    env, params = make_env(load_config(CONFIG, ["env={}", *sets]))
    run = Evaluator(env, params, lambda k, o, s, p, a: scripted_policy(env)(k, o, s, p), batch=2)(
        jax.random.PRNGKey(1), 2)
    assert run.n == 2 and np.all(run.length > 0)
    assert run.returns.dtype == np.float64 and all(v.dtype == np.float64 for v in run.terms.values())
    np.testing.assert_allclose(sum(run.terms.values()), run.returns, rtol=1e-9, atol=1e-9)


def test_tether_tensions_of_tethers_without_interior_masses():
    """A tether with ``n_masses: 0`` is one segment from the knot to the UAV's marker: the
    report's tension (from the saved columns: the marker moved with the body's pose and
    body-frame angular velocity, numpy) equals the spring law at the simulator's own node
    states (marker kinematics of mysim_jax.dynamics.markers) over a recorded episode."""
    from mysim_jax.dynamics.forces import spring_tension
    from mysim_jax.dynamics.markers import node_states
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.episode import record_columns, record_episode
    from mysim_jax.tasks.evaluate import scripted_policy
    from mysim_jax.tasks.outcome import tether_tensions

    config = load_config(CONFIG, ["env={}", *SMALL, "net.tethers.n_masses=0", "sim.t_end=0.8"])
    env, params = make_env(config)
    rec = record_episode(env, params, scripted_policy(env), jax.random.PRNGKey(4), 0)
    got = tether_tensions(record_columns(env, rec), env.scene, rec.sim_params, config)
    scene, sp = env.scene, rec.sim_params
    pos, vel = jax.vmap(lambda ph: node_states(scene, sp, ph))(rec.trajectory.phys)
    pos, vel = np.asarray(pos, float), np.asarray(vel, float)
    assert len(got) == len(config.net.tethers.uavs) == 4
    for n, uav in enumerate(config.net.tethers.uavs):
        k = scene.spring_names.index(f"{config.net.name}_t{n}[0]")
        a, b = scene.spring_node_a[k], scene.spring_node_b[k]
        d, dv = pos[:, b] - pos[:, a], vel[:, b] - vel[:, a]
        length = np.linalg.norm(d, axis=-1)
        rate = np.einsum("ij,ij->i", dv, d / length[:, None])
        want = np.asarray(spring_tension(float(sp.spring_stiffness[k]), float(sp.spring_damping[k]),
                                         float(sp.spring_rest_length[k]), length, rate,
                                         (scene.spring_tension_only[k],)))
        assert want.max() > 0.02                                  # the tethers were taut
        # measured: 1.2e-5 N of 0.1-0.2 N (float32 states; the report computes in float64)
        np.testing.assert_allclose(got[uav], want, rtol=0, atol=1e-3 * want.max())
