"""The side-by-side physics of a scripted catch (mysim_jax/bench/levels.py), which BENCHMARKS.md
(i) reports per fidelity level: checked against the same episode recorded with
``record_episode`` and reduced in NumPy by separate code (the tether tension by
``tasks.outcome.tether_tensions``, the spring law re-evaluated from the saved columns)."""

import jax
import numpy as np
import pytest

from mysim_jax.bench import levels
from mysim_jax.config.scene import load_config
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.episode import record_columns, record_episode
from mysim_jax.tasks.evaluate import scripted_policy
from mysim_jax.tasks.outcome import tether_tensions

from conftest import CONFIGS

SCENE = CONFIGS / "capture_env_falling.yaml"


def _xyz(columns, name):
    return np.stack([columns[f"{name}_{a}"] for a in "xyz"], axis=-1)


def test_catch_measures_match_a_recorded_episode_reduced_in_numpy():
    config = load_config(SCENE, ["level=train", "env.policy_rate=125.0", "sim.t_end=1.2"])
    env, params = make_env(config)
    key = jax.random.PRNGKey(3)
    rows = levels.catch_measures(env, params, config.net, key, 2, chunk=2)
    record = record_episode(env, params, scripted_policy(env), key, index=1)
    columns = record_columns(env, record)
    n = record.length
    net = config.net
    g = net.knots
    centre = np.mean([_xyz(columns, net.knot_name(i, j)) for i in (g // 2 - 1, g // 2) for j in (g // 2 - 1, g // 2)],
                     axis=0)
    corners = np.stack([_xyz(columns, net.knot_name(*k)) for k in net.tether_knots()], axis=1)
    sag = corners[..., 2].mean(axis=1) - centre[:, 2]
    size = np.mean([np.linalg.norm(corners[:, i] - corners[:, (i + 1) % 4], axis=-1) for i in range(4)], axis=0)
    tension = np.max(np.stack(list(tether_tensions(columns, env.scene, record.sim_params, config).values())), axis=0)
    # rows hold the state after each step: the recorded trajectory's rows 1 .. n. The two
    # runs are different compiled programs; over the first 0.25 s (before the target reaches
    # the net) they agree to float32 round-off (beyond that the slack net's round-off grows
    # to millimetres). The tension's floor is k x 1e-6 m of float32 positions ~3 m apart.
    w = slice(0, 32)
    assert n > 32 and not record.touching[w].any() and tension[1:33].max() > 5e-3
    np.testing.assert_allclose(rows["target"][1, w], _xyz(columns, config.target.name)[1:33], atol=2e-6)
    np.testing.assert_allclose(rows["centre"][1, w], centre[1:33], atol=2e-6)
    np.testing.assert_allclose(rows["sag"][1, w], sag[1:33], atol=2e-6)
    np.testing.assert_allclose(rows["size"][1, w], size[1:33], atol=2e-6)
    np.testing.assert_allclose(rows["tension"][1, w], tension[1:33], atol=1e-4)
    assert np.all(rows["tension"][1, :n] >= 0.0) and np.all(rows["size"][1, :n] > 1.0)


def test_summary_and_trajectory_difference_on_hand_built_rows():
    steps = 6
    z = np.array([5.0, 4.0, 3.2, 3.0, 3.1, 3.05])
    rows = {"target": np.zeros((1, steps, 3)), "centre": np.zeros((1, steps, 3)),
            "sag": np.linspace(0.4, 0.5, steps)[None], "size": np.full((1, steps), 1.9),
            "tension": np.array([[0.1, 0.2, 0.9, 2.5, 1.0, 9.0]]),
            "touching": np.array([[False, False, True, True, True, True]]),
            "done": np.array([[False, False, False, False, True, True]])}
    rows["target"][0, :, 2] = z
    s = levels.summarize(rows, 0)
    assert s.length == 5 and s.touched
    assert s.sag == pytest.approx(rows["sag"][0, 2]) and s.size == pytest.approx(1.9)
    assert s.stopping_distance == pytest.approx(3.2 - 3.0)
    assert s.peak_tension == pytest.approx(2.5)          # the step after the end does not count
    other = {k: v.copy() for k, v in rows.items()}
    other["target"][0, :, 0] += np.array([0.0, 0.0, 0.3, 0.4, 0.0, 5.0])
    other["done"] = np.array([[False, False, False, True, True, True]])   # ends one step sooner
    rms, largest = levels.trajectory_difference(other, rows, 0, "target")
    assert largest == pytest.approx(0.4) and rms == pytest.approx(np.sqrt((0.09 + 0.16) / 4))
    rows["touching"][:] = False
    never = levels.summarize(rows, 0)
    assert not never.touched and np.isnan(never.stopping_distance) and never.peak_tension == pytest.approx(2.5)


def test_the_side_by_side_table_reads_the_rows():
    def rows(offset, touch_at):
        steps = 4
        target = np.zeros((2, steps, 3))
        target[:, :, 2] = [[5.0, 4.0, 3.0, 2.9], [5.0, 4.0, 3.5, 3.2]]
        target[:, :, 0] = offset
        touching = np.zeros((2, steps), bool)
        touching[:, touch_at:] = True
        return {"target": target, "centre": np.zeros((2, steps, 3)), "sag": np.full((2, steps), 1.0),
                "size": np.full((2, steps), 1.5), "tension": np.full((2, steps), 4.0), "touching": touching,
                "done": np.zeros((2, steps), bool)}

    table = levels.catch_table({"full": rows(0.0, 2), "cheap": rows(0.3, 1)}, rate=50.0, seed=7)
    assert "episodes 0–1 of one draw (seed 7) at a policy rate of 50 Hz (rows every 20 ms" in table[0]
    full, cheap = table[-2].split(" | "), table[-1].split(" | ")
    assert full[:6] == ["| full", "2 of 2", "1.000", "1.500", "0.200", "4.00"] and full[6:] == ["–", "– |"]
    # stopping distance from the first touch: 4.0 - 2.9 and 4.0 - 3.2, median 0.95; target 0.3 m off
    assert cheap[:6] == ["| cheap", "2 of 2", "1.000", "1.500", "0.950", "4.00"]
    assert cheap[6] == "0.300 / 0.300" and cheap[7] == "0.000 / 0.000 |"
