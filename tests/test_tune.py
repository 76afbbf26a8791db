"""Tuning a capture scene's scripted team (mysim_jax/grad/tune.py, scripts/tune.py): a
tiny random search spends at most its budget and never ends worse than the configured
team on the same episodes, ``v = 0`` is the configured team, the box stays inside what
the team config accepts, and the script refuses bad input before compiling."""

from __future__ import annotations


import numpy as np
import pytest

from conftest import CONFIGS, only_array_ops, run_script_main
from mysim_jax.config.capture import TeamConfig
from mysim_jax.config.scene import load_config
from mysim_jax.grad.search import METHODS
from mysim_jax.grad.team import TeamParameters
from mysim_jax.grad.tune import TuningProblem, config_box, team_block, tune, tuned_fields, tuned_team
from mysim_jax.tasks.capture import make_env

# test_gradmap.py's small falling scene (a 3 x 3-knot net, velocity setpoints at a 10 Hz
# policy: the VelocityTeam) in float32
SMALL = ["level=train", "net.knots=3", "output.plot=[target, uav0]", "env.policy_rate=10.0",
         *[f"quadrotors.{i}.controller.setpoint_mode=velocity" for i in range(4)],
         *[f"quadrotors.{i}.controller.max_speed=5.0" for i in range(4)]]


@pytest.fixture(scope="module")
def small():
    config = load_config(CONFIGS / "capture_env_falling.yaml", SMALL)
    env, params = make_env(config)
    return config, env, TuningProblem(env, params, episodes=2, horizon=3, seed=1)


def test_a_tiny_random_search_spends_its_budget_and_is_no_worse_than_the_configured_team(small):
    config, env, problem = small
    assert problem.steps_per_evaluation == 6
    assert "catch_height" not in problem.names and "net_drop" not in problem.names   # not in team:
    budget = 4 * problem.steps_per_evaluation + 5                   # 2 batches of 2, and change
    spent = []
    result = tune(problem, "random", budget, batch=2, seed=3, progress=spent.append)
    assert result.team_steps == sum(spent) == 4 * problem.steps_per_evaluation <= budget
    nominal = problem.evaluate(np.zeros((1, problem.size)))[0]     # padded to the search's 2 candidates
    mixed = problem.evaluate(np.stack([np.zeros(problem.size), result.best_u]))
    assert mixed[0] == nominal and mixed[1] == result.best_value    # the same fixed episodes for each
    assert result.best_value <= nominal
    assert np.all(result.best_u >= problem.lower) and np.all(result.best_u <= problem.upper)
    if np.any(result.best_u != 0.0):                                # another candidate won: it differs
        assert not np.allclose(list(tuned_fields(problem, result.best_u).values()), problem.nominal)
    # v = 0 is the configured team, field for field
    same = tuned_team(problem, np.zeros(problem.size))
    assert same == env.scripted and all(type(getattr(same, n)) is float for n in problem.names)
    block = team_block(problem, np.zeros(problem.size), "scripted")
    configured = config.team or TeamConfig()
    for name, value in block.items():
        if name != "policy" and name != "altitude":
            assert value == pytest.approx(getattr(configured, name), rel=1e-3), name


def test_the_gradient_matches_a_central_difference_along_it(small):
    _, _, problem = small
    v = np.linspace(-0.1, 0.1, problem.size)
    value, grad = problem.value_and_grad(v)
    direction = grad / np.linalg.norm(grad)
    h = 0.02
    plus, minus = problem.evaluate(np.stack([v + h * direction, v - h * direction]))   # the search's shape
    assert value == pytest.approx(float(problem.evaluate(np.stack([v, v]))[0]), rel=1e-5)
    assert np.linalg.norm(grad) > 1e-3
    # measured: 0.5826 against |grad| 0.5830 (0.06 %; mostly the altitude's component)
    assert (plus - minus) / (2 * h) == pytest.approx(np.linalg.norm(grad), rel=0.01)


def test_the_box_stays_inside_the_team_configs_checks():
    team = TeamParameters(names=("close", "climb_radius", "lead", "gain"), nominal=(0.3, 0.5, 0.0, 2.0),
                          scale=(0.3, 0.5, 0.1, 2.0))
    lower, upper = config_box(team, team.names, -0.5, 0.5)
    values = lambda v: np.asarray(team.nominal) + np.asarray(team.scale) * v     # noqa: E731
    lo, hi = values(lower), values(upper)
    assert hi[0] < lo[1]                                           # close < climb_radius everywhere
    assert lo[2] == 0.0 and hi[2] == pytest.approx(0.05)           # lead >= 0
    assert lo[3] > 0.0 and (lower[3], upper[3]) == (-0.5, 0.5)     # gain > 0, untouched
    TeamConfig(policy="chase", close=hi[0], climb_radius=lo[1], lead=lo[2], gain=lo[3])


def test_the_scripts_methods_are_the_searchs():
    import importlib.util

    from conftest import ROOT

    spec = importlib.util.spec_from_file_location("_tune_script", ROOT / "scripts" / "tune.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.METHODS == METHODS


@pytest.mark.parametrize("args, message", [
    (["--method", "adam", "--budget", "1000"], "--method 'adam'"),
    (["--method", "random", "--budget", "10"], "less than one evaluation"),
    (["--method", "grad", "--budget", "1000", "--horizon-s", "60"], "--horizon-s 60"),
    (["--method", "grad", "--budget", "1000", "--truncate", "0"], "--truncate 0"),
    (["--method", "cmaes", "--budget", "1000", "--box", "0.1", "0.5"], "--box"),
    (["--method", "random", "--budget", "1000", "--episodes", "0"], "--episodes 0"),
    (["--method", "random", "--budget", "1000", "--ground-weight", "-1"], "--ground-weight -1: must be >= 0"),
])
def test_the_script_refuses_bad_input_before_compiling(tmp_path, capsys, args, message):
    out = tmp_path / "tune"
    code, _, err, compiled = run_script_main("tune", [CONFIGS / "capture_env_maneuvering.yaml", *args,
                                                      "--out", out, "--no-progress"], capsys)
    assert code == 2 and message in err and err.startswith("error:"), err
    assert only_array_ops(compiled) and not out.exists()


def test_the_script_refuses_a_missing_file(tmp_path, capsys):
    out = tmp_path / "tune"
    code, _, err, compiled = run_script_main("tune", [tmp_path / "nowhere.yaml", "--method", "random",
                                                      "--budget", "1000", "--out", out], capsys)
    assert code == 2 and "nowhere.yaml" in err and not out.exists() and only_array_ops(compiled)
