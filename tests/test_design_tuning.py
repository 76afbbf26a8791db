"""Tuning a capture scene's design (mysim_jax/grad/design.py, ``scripts/tune.py --design``):
the tethered UAVs' starts follow the net's corners and the tethers' length (checked against
positions computed here from the YAML's numbers, not with the package's net builder), the
episodes' draws do not depend on the design, a design judged against itself differs by
exactly nothing, and bad input is refused before anything compiles."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from conftest import CONFIGS, run_script_main
from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.grad.design import DesignField, DesignProblem, design_overrides
from mysim_jax.tasks.capture import make_env

SCENE = CONFIGS / "capture_env_falling.yaml"
TRAIN = CONFIGS / "train_capture_falling.yaml"


def _loader(level="train", extra=()):
    return lambda overrides: load_config(SCENE, [*extra, *overrides, f"level={level}"])


def test_a_design_field_reads_key_low_high_and_refuses_the_rest():
    assert DesignField.parse("net.size=1.5:3.5") == DesignField("net.size", 1.5, 3.5)
    assert DesignField.parse(" net.tethers.length = 0.6 : 2 ") == DesignField("net.tethers.length", 0.6, 2.0)
    for text, says in (("net.size=1.5-3", "KEY=LOW:HIGH"), ("net.size=a:3", "numbers"),
                       ("net.size=3:2", "LOW < HIGH"), ("net.size=1:inf", "LOW < HIGH"),
                       ("sim.dt=1e-3:2e-3", "not a design value"), ("level=1:2", "not a design value")):
        with pytest.raises(ValueError, match=says):
            DesignField.parse(text)


def test_the_tethered_uavs_start_with_their_knots_and_the_tethers_length():
    """From the YAML's numbers (net centre, size, knots, spread, the UAVs' starts): each
    UAV's corner knot sits at centre +- spread * size / 2, and the UAV keeps its offset from
    it scaled by the new tether length over the old."""
    config = load_config(SCENE)
    cx, cy, cz = config.net.center
    half = 0.5 * config.net.spread * config.net.size
    new_size, new_length = 2.9, 1.6
    overrides = design_overrides(config, {"net.size": new_size, "net.tethers.length": new_length})
    moved = load_config(SCENE, overrides)
    assert moved.net.size == new_size and moved.net.tethers.length == new_length
    new_half = 0.5 * config.net.spread * new_size
    for k, body in enumerate(config.bodies[:4]):
        x, y, z = body.pos
        sx, sy = np.sign(x - cx), np.sign(y - cy)              # the corner the UAV starts over
        old_knot = np.array([cx + sx * half, cy + sy * half, cz])
        new_knot = np.array([cx + sx * new_half, cy + sy * new_half, cz])
        want = new_knot + (np.array(body.pos) - old_knot) * new_length / config.net.tethers.length
        np.testing.assert_allclose(moved.bodies[k].pos, want, atol=1e-12)
        # the tether starts as slack as configured: span / length unchanged (the 1 cm
        # attachment below the centre aside)
        span_old = np.linalg.norm(np.array(body.pos) - old_knot) / config.net.tethers.length
        span_new = np.linalg.norm(np.array(moved.bodies[k].pos) - new_knot) / new_length
        assert span_new == pytest.approx(span_old, rel=1e-12)
    # a value that does not move the net leaves the bodies alone
    assert design_overrides(config, {"contact.damping": 0.1}) == ["contact.damping=0.1"]


def test_the_episodes_draws_do_not_depend_on_the_design():
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    starts = []
    for values in ({}, {"net.size": 3.0, "net.tethers.length": 1.5}):
        config = load_config(SCENE, [*design_overrides(load_config(SCENE), values), "level=train"])
        env, params = make_env(config)
        starts.append([env.reset(k, params)[1] for k in keys])
    for a, b in zip(*starts):
        np.testing.assert_array_equal(a.sim.phys.body_pos[env.target_body], b.sim.phys.body_pos[env.target_body])
        np.testing.assert_array_equal(a.sim.phys.body_vel[env.target_body], b.sim.phys.body_vel[env.target_body])
        np.testing.assert_array_equal(a.sim.phys.body_pos[:4] != b.sim.phys.body_pos[:4], True)   # UAVs moved


def test_the_problem_refuses_what_it_cannot_tune():
    with pytest.raises(ConfigError, match="level train sets this value"):
        DesignProblem(_loader(), [DesignField("net.line.EA", 10.0, 3000.0)])
    with pytest.raises(ValueError, match="must be inside the bounds"):
        DesignProblem(_loader(), [DesignField("net.size", 2.5, 3.5)])
    with pytest.raises(ConfigError, match="not a real number"):
        DesignProblem(_loader(), [DesignField("net.knots", 6.0, 10.0)])
    with pytest.raises(ConfigError, match="no such value"):
        DesignProblem(_loader(), [DesignField("net.mesh", 1.0, 2.0)])
    with pytest.raises(ValueError, match="twice"):
        DesignProblem(_loader(), [DesignField("net.size", 1.5, 3.0), DesignField("net.size", 1.0, 3.0)])
    # a bound whose scene does not load (a tether too short for the UAV's 0.9 m climb
    # is fine, it moves; a contact damping below zero is not)
    with pytest.raises(ConfigError, match="contact.damping"):
        DesignProblem(_loader(), [DesignField("contact.damping", -1.0, 1.0)])
    problem = DesignProblem(_loader(), [DesignField("net.size", 1.5, 3.5), DesignField("net.tethers.length", 0.5, 2.0)])
    np.testing.assert_allclose(problem.lower, [1.5 / 2.0 - 1, 0.5 - 1])
    np.testing.assert_allclose(problem.upper, [3.5 / 2.0 - 1, 2.0 - 1])
    assert problem.values_dict(np.zeros(2)) == {"net.size": 2.0, "net.tethers.length": 1.0}


@pytest.mark.parametrize("args, says", [
    (["--method", "grad"], "expected one of cmaes, random"),
    (["--method", "cmaes", "--truncate", "3"], "--truncate is for tuning the team"),
    (["--method", "cmaes", "--box", "-1", "1"], "--box is for tuning the team"),
    (["--method", "cmaes", "--budget", "10"], "less than one design's evaluation"),
])
def test_the_script_refuses_bad_design_input_before_compiling(tmp_path, capsys, args, says):
    argv = [TRAIN, "--design", "net.size=1.5:3.5", "--out", tmp_path / "out", *args]
    if "--budget" not in args:
        argv += ["--budget", "100000"]
    code, _, err, compiled = run_script_main("tune", argv, capsys)
    assert code == 2 and says in err and not compiled and not (tmp_path / "out").exists()


def test_a_design_judged_against_itself_differs_by_nothing(tmp_path, capsys):
    """A search of one evaluation (random search's first candidate is the configured
    design), then the judging of that design against the configured one on the same
    episodes: the same scene, so exactly the same outcomes."""
    out = tmp_path / "design"
    code, stdout, err, _ = run_script_main("tune", [
        TRAIN, "--design", "net.size=1.5:3.5", "--method", "random", "--batch", "1", "--episodes", "2",
        "--budget", "20", "--judge-episodes", "3", "--judge-level", "train", "--judge-batch", "3",
        "--set", "sim.t_end=1.0", "--out", out, "--no-progress"], capsys)
    assert code == 0, err
    record = json.loads((out / "tune.json").read_text())
    judged = json.loads((out / "judged.json").read_text())
    assert record["candidates_evaluated"] == 1 and record["best_u"] == [0.0]      # the nominal, flown once
    assert record["best_value"] == record["nominal_value"] and 0.0 <= record["best_value"] <= 1.0
    assert record["team_steps"] == 2 * 10 and record["set"][0] == "net.size=2.0"
    configured = load_config(TRAIN.parent / "capture_env_falling.yaml")
    for entry in record["set"][1:]:                                  # the UAVs' starts, unmoved
        k = int(entry.split(".")[1])
        np.testing.assert_allclose(json.loads(entry.split("=", 1)[1]), configured.bodies[k].pos, atol=1e-12)
    assert judged["success_per_episode"]["tuned"] == judged["success_per_episode"]["configured"]
    assert judged["difference"]["estimate"] == 0.0 and judged["episodes"] == 3
    assert (out / "tune_best.png").stat().st_size > 0 and "as --set" in stdout
