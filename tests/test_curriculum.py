"""The training curriculum over the evading target's difficulty (``env.curriculum`` of a
training file): its checks, its stage rule, the ranges it hands the trainer, and one tiny
run through scripts/train.py."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.config import CurriculumConfig, load_scene, train_config_from_dict
from mysim_jax.mappo.curriculum import Curriculum

ROOT = Path(__file__).resolve().parents[1]
TRAIN_FILE = ROOT / "configs" / "train_capture_maneuvering.yaml"


def _config(curriculum, **extra):
    raw = {"name": "c", "env": {"scene": "capture_env_maneuvering.yaml", "curriculum": curriculum}, **extra}
    return train_config_from_dict(raw, str(ROOT / "configs" / "t.yaml"))


@pytest.mark.parametrize("curriculum, message", [
    ({"stages": [0.5, 0.25, 1.0]}, r"env.curriculum: stages \[0.5, 0.25, 1.0\] must increase"),
    ({"stages": [0.25, 0.5]}, r"env.curriculum: stages \[0.25, 0.5\] never reach the full range"),
    ({"stages": [0.5, 1.0], "advance_success": None}, "never leaves its first stage"),
    ({"stages": [0.0, 1.0]}, r"env.curriculum.stages.0: Input should be greater than 0"),
    ({"stages": [0.5, 1.5]}, r"env.curriculum.stages.1: Input should be less than or equal to 1"),
    ({"stages": []}, r"env.curriculum.stages"),
    ({"stages": [0.5, 1.0], "advance_success": 1.5}, r"env.curriculum.advance_success"),
    ({"stages": [0.5, 1.0], "window": 0}, r"env.curriculum.window"),
    ({"stages": [0.5, 1.0], "speed": 2}, r"env.curriculum.speed"),
])
def test_bad_curricula_are_one_line_errors_naming_the_field(curriculum, message):
    with pytest.raises(ConfigError, match=message):
        _config(curriculum)


def test_a_curriculum_that_cannot_reach_the_full_range_in_the_run_is_refused():
    # 3 stage changes of 100 iterations, but the run has 300 / (64 x 16 / 1024) ... iterations
    with pytest.raises(ConfigError, match=r"env.curriculum.max_iterations: 3 stage changes of 100 iterations need "
                                          r"301 iterations.*the run has 30 "):
        _config({"stages": [0.25, 0.5, 0.75, 1.0], "advance_success": None, "max_iterations": 100},
                algo={"num_envs": 32, "num_steps": 32, "total_env_steps": 30 * 1024})
    # with a success rule as well it may still advance sooner: accepted
    _config({"stages": [0.25, 0.5, 0.75, 1.0], "max_iterations": 100},
            algo={"num_envs": 32, "num_steps": 32, "total_env_steps": 30 * 1024})


def test_a_curriculum_needs_an_evading_target_and_a_scene():
    falling = train_config_from_dict({"name": "c", "env": {"scene": "capture_env_falling.yaml",
                                                           "curriculum": {"stages": [0.5, 1.0]}}},
                                     str(ROOT / "configs" / "t.yaml"))
    with pytest.raises(ConfigError, match=r"env.curriculum scales an evading target.*'falling'"):
        load_scene(falling, ROOT / "configs" / "t.yaml")
    with pytest.raises(ConfigError, match="curriculum scales a capture scene's evading target, not a builtin"):
        train_config_from_dict({"name": "c", "env": {"builtin": "reach", "curriculum": {"stages": [1.0]}}})


def test_the_stage_rule():
    cfg = CurriculumConfig(stages=[0.25, 0.5, 1.0], advance_success=0.8, window=3, max_iterations=10)
    cur = Curriculum(cfg)
    assert cur.fraction == 0.25 and not cur.last_stage
    # the window's mean must reach the threshold over `window` iterations; NaN (no episode
    # ended) is skipped, not counted as 0
    assert [cur.update(x) for x in (0.9, float("nan"), 0.9)] == [False, False, False]
    assert cur.update(0.7) is True and cur.stage == 1 and cur.fraction == 0.5      # (0.9 + 0.9 + 0.7) / 3
    assert [cur.update(0.0) for _ in range(9)] == [False] * 9
    assert cur.update(0.0) is True and cur.stage == 2                              # 10 iterations in the stage
    assert cur.last_stage and cur.update(1.0) is False and cur.stage == 2          # stays at the full range
    # success only / iterations only
    only = Curriculum(CurriculumConfig(stages=[0.5, 1.0], advance_success=None, max_iterations=2))
    assert [only.update(1.0), only.update(1.0)] == [False, True]
    never = Curriculum(CurriculumConfig(stages=[0.5, 1.0], advance_success=0.9, window=2))
    assert not any(never.update(0.85) for _ in range(50)) and never.stage == 0


def test_a_resumed_curriculum_continues_as_the_uninterrupted_one():
    cfg = CurriculumConfig(stages=[0.25, 0.5, 1.0], advance_success=0.7, window=2, max_iterations=6)
    rates = [0.1, 0.8, 0.9, 0.2, float("nan"), 0.3, 0.5, 0.1, 0.9, 0.9, 0.95]
    whole, rows = Curriculum(cfg), [{"iteration": 0, "select_success": 0.5}]     # the selection row: skipped
    for i, r in enumerate(rates):
        rows.append({"iteration": i + 1, "success_rate": "" if math.isnan(r) else r, "curriculum_stage": whole.stage})
        whole.update(r)
        again = Curriculum.resumed(cfg, rows)
        assert (again.stage, again.iterations_in_stage, again._recent) == \
            (whole.stage, whole.iterations_in_stage, whole._recent)
    assert whole.stage == 2


def test_scaled_ranges_scale_the_target_s_difficulty_only_and_resets_draw_from_them():
    from mysim_jax.config.scene import load_config
    from mysim_jax.tasks.capture import TARGET_DIFFICULTY, make_env, scaled_target_ranges

    env, params = make_env(load_config(ROOT / "configs" / "capture_env_maneuvering.yaml"))
    ranges = scaled_target_ranges(params.ranges, 0.25)
    for side in ("low", "high"):
        full, scaled = getattr(params.ranges, side), getattr(ranges, side)
        for field in TARGET_DIFFICULTY:
            np.testing.assert_allclose(getattr(scaled, field), 0.25 * np.asarray(getattr(full, field)), rtol=1e-6)
        for field in ("target_mass", "uav_mass_scale", "wind_force"):
            np.testing.assert_array_equal(getattr(scaled, field), getattr(full, field))
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params.replace(ranges=ranges))
    speed = np.asarray(states.episode.max_speed)
    assert speed.min() >= 0.25 * 2.0 - 1e-6 and speed.max() <= 0.25 * 3.5 + 1e-6 and np.ptp(speed) > 0.1


def test_train_script_runs_a_curriculum_and_logs_it(tmp_path):
    """Three iterations of 4 environments x 2 steps on the evading task, a curriculum of
    three stages advanced every iteration: the stages and fractions logged per iteration,
    the change announced, the summary's first full-range iteration, the curves drawn. No
    final evaluation (``--no-eval``): the curriculum does not reach it, and tests/
    test_train_script.py runs one on the capture environment."""
    out = tmp_path / "run"
    sets = ["algo.num_envs=4", "algo.num_steps=2", "algo.total_env_steps=24", "algo.num_minibatches=2",
            "algo.init=none", "run.selection=null",
            "env.curriculum={stages: [0.25, 0.5, 1.0], advance_success: null, max_iterations: 1}"]
    env = {**os.environ, "JAX_LOG_COMPILES": "1"}
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), str(TRAIN_FILE), "--out", str(out),
                          "--no-progress", "--no-eval", *[a for s in sets for a in ("--set", s)]],
                         capture_output=True, text=True, cwd=ROOT, env=env)
    assert res.returncode == 0, res.stderr
    # the stage changes hand the compiled iteration new ranges: it is compiled once
    compiles = [ln for ln in res.stderr.splitlines() if "Compiling" in ln and "_iteration" in ln]
    assert len(compiles) == 1, compiles
    assert "curriculum: stage 1 of 3 (the target's speed, jink and flee ranges x 0.25)" in res.stdout
    assert "curriculum: stage 2 of 3 from iteration 2 (ranges x 0.5)" in res.stdout
    with (out / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(int(r["iteration"]), int(r["curriculum_stage"]), float(r["curriculum_fraction"])) for r in rows] == \
        [(1, 0, 0.25), (2, 1, 0.5), (3, 2, 1.0)]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["curriculum"] == {"stages": [0.25, 0.5, 1.0], "final_stage": 2, "full_range_from_iteration": 3}
    assert (out / "curves.png").stat().st_size > 10_000
