"""No input is silently ignored: a scene value that a per-episode draw replaces, the old
name of the per-episode wind force, and a trained policy flown on an environment whose
observations and actions mean something else are each a one-line error naming what to do."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest

from mysim_jax.config.env import drawn_value_problems
from mysim_jax.config.scene import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[1]
FALLING = ROOT / "configs" / "capture_env_falling.yaml"
MANEUVERING = ROOT / "configs" / "capture_env_maneuvering.yaml"
POLICY = ROOT / "docs" / "train" / "falling" / "policy"


def _evaluate():
    spec = importlib.util.spec_from_file_location("_evaluate_script", ROOT / "scripts" / "evaluate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path, override, draw", [
    (FALLING, "target.mass=0.5", "env.randomize.target_mass"),
    (MANEUVERING, "target.propulsion.max_speed=4.2", "env.randomize.max_speed"),
    (MANEUVERING, "target.propulsion.jink_acceleration=6", "env.randomize.jink_acceleration"),
    (MANEUVERING, "target.propulsion={max_speed: 4.2, flee_acceleration: 3}", "env.randomize.max_speed"),
])
def test_a_value_a_draw_replaces_is_an_error(path, override, draw):
    config = load_config(path, [override])
    problems = drawn_value_problems(config, [override])
    assert problems and draw in problems[0] and "would be ignored" in problems[0]
    key, value = override.split("=", 1)
    if not value.startswith("{"):
        # the fix it names works: the draw fixed at the value, or the draw turned off
        assert f"{draw}={{low: {value}, high: {value}}}" in problems[0]
        fixed = [f"{draw}={{low: {value}, high: {value}}}"]
        assert not drawn_value_problems(load_config(path, fixed), fixed)
        off = [override, f"{draw}=null"]
        assert not drawn_value_problems(load_config(path, off), off)


def test_evaluate_refuses_an_ignored_override(tmp_path, capsys):
    code = _evaluate().main([str(FALLING), "--policy", "scripted", "--episodes", "2", "--out", str(tmp_path / "o"),
                             "--set", "target.mass=0.5"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "env.randomize.target_mass" in err and "{low: 0.5, high: 0.5}" in err
    assert not (tmp_path / "o").exists()


def test_a_training_file_that_sets_a_drawn_value_is_refused(tmp_path):
    from mysim_jax.mappo.config import load_train_config

    shutil.copy(FALLING, tmp_path / "scene.yaml")
    (tmp_path / "train.yaml").write_text("name: t\nenv:\n  scene: scene.yaml\n  set: ['target.mass=0.5']\n")
    with pytest.raises(ConfigError, match=r"train.yaml: env.set: target.mass=0.5: env.randomize.target_mass"):
        load_train_config(tmp_path / "train.yaml")


def test_the_wind_draw_is_named_a_force():
    with pytest.raises(ConfigError, match="renamed wind_force .a force in N on every UAV, not a wind speed"):
        load_config(FALLING, ["env.randomize.wind={low: [0, 0, 0], high: [0, 0, 0]}"])
    config = load_config(FALLING)
    assert config.env.randomize.wind_force is not None


def test_a_policy_on_an_environment_it_was_not_trained_for_is_refused(tmp_path, capsys):
    """The falling policy (velocity setpoints at 10 Hz) on the scene file's own environment
    (position setpoints at 25 Hz): an error naming both differences, before compiling."""
    code = _evaluate().main([str(FALLING), "--policy", str(POLICY), "--episodes", "2", "--out",
                             str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "setpoint mode: trained with velocity setpoints, this environment has position setpoints" in err
    assert "policy rate: trained with 10 Hz, this environment has 25 Hz" in err
    assert "--allow-mismatch" in err and not (tmp_path / "o").exists()


def test_the_policy_check_passes_on_its_own_scene_and_when_allowed(tmp_path):
    from mysim_jax.mappo.policies import PolicyError, make_checked_policy
    from mysim_jax.tasks.capture import make_env

    own, own_params = make_env(load_config(POLICY.parent / "scene.yaml"))
    make_checked_policy(own, own_params, str(POLICY))
    # another level of the same scene is not a mismatch (evaluations on full do that)
    from mysim_jax.mappo.config import load_scene, load_train_config

    path = ROOT / "configs" / "train_capture_falling.yaml"
    train, train_params = make_env(load_scene(load_train_config(path), path, level="train"))
    assert train.level == "train"
    make_checked_policy(train, train_params, str(POLICY))
    other, other_params = make_env(load_config(FALLING))
    with pytest.raises(PolicyError, match="setpoint mode"):
        make_checked_policy(other, other_params, str(POLICY))
    make_checked_policy(other, other_params, str(POLICY), allow_mismatch=True)
    # a policy that records no environment cannot be checked: it says so
    old = tmp_path / "old"
    shutil.copytree(POLICY, old)
    meta = json.loads((old / "policy.json").read_text())
    del meta["environment"]
    (old / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(PolicyError, match="does not record the environment.*--allow-mismatch"):
        make_checked_policy(own, own_params, str(old))


def test_the_observation_layout_covers_the_observation():
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.contract import environment_contract, observation_layout

    env, params = make_env(load_config(FALLING))
    assert sum(w for _, w in observation_layout(env)) == env.obs_size
    contract = environment_contract(env, params)
    assert contract["setpoint_mode"] == "position" and contract["policy_rate_hz"] == 25.0
    assert json.loads(json.dumps(contract)) == contract
