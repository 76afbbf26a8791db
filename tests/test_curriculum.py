"""The training curriculum over the evading target's difficulty (``env.curriculum`` of a
training file): its checks, its stage rule, the ranges it hands the trainer, and one tiny
run through scripts/train.py."""

from __future__ import annotations

import csv
import json
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
    cs = cur.start()
    assert cur.fraction(cs) == 0.25 and not cur.last_stage(cs)

    def feed(rates):
        nonlocal cs
        moved = []
        for rate in rates:
            cs, m = cur.update(cs, rate)
            moved.append(m)
        return moved

    # the window's mean must reach the threshold over `window` iterations; NaN (no episode
    # ended) is skipped, not counted as 0
    assert feed([0.9, float("nan"), 0.9]) == [False, False, False]
    assert feed([0.7]) == [True] and int(cs.stage) == 1 and cur.fraction(cs) == 0.5     # (0.9 + 0.9 + 0.7) / 3
    assert int(cs.iterations_in_stage) == 0 and int(cs.n_recent) == 0                   # the new stage starts afresh
    assert feed([0.0] * 9) == [False] * 9
    assert feed([0.0]) == [True] and int(cs.stage) == 2                                  # 10 iterations in the stage
    assert cur.last_stage(cs) and feed([1.0]) == [False] and int(cs.stage) == 2          # stays at the full range
    # success only / iterations only
    only = Curriculum(CurriculumConfig(stages=[0.5, 1.0], advance_success=None, max_iterations=2))
    cs_only = only.start()
    cs_only, first = only.update(cs_only, 1.0)
    cs_only, second = only.update(cs_only, 1.0)
    assert [first, second] == [False, True]
    never = Curriculum(CurriculumConfig(stages=[0.5, 1.0], advance_success=0.9, window=2))
    cs_never = never.start()
    for _ in range(50):
        cs_never, moved = never.update(cs_never, 0.85)
        assert not moved
    assert int(cs_never.stage) == 0 and int(cs_never.n_recent) == 2 and int(cs_never.iterations_in_stage) == 50


def test_a_state_outside_the_stages_is_refused():
    cur = Curriculum(CurriculumConfig(stages=[0.5, 1.0], max_iterations=2))
    with pytest.raises(ValueError, match="curriculum stage 2 of 2"):
        cur.fraction(cur.start().replace(stage=jax.numpy.int32(2)))


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


CURRICULUM_RUN = ["algo.num_envs=4", "algo.num_steps=2", "algo.total_env_steps=24", "algo.num_minibatches=2",
                  "algo.init=bc", "algo.bc.num_envs=4", "algo.bc.steps=4", "algo.bc.epochs=1",
                  "algo.bc.critic_warmup=1", "run.selection=null", "run.checkpoint_every=1", "run.keep_checkpoints=3",
                  "env.curriculum={stages: [0.25, 0.5, 1.0], advance_success: null, max_iterations: 1}",
                  "run.then=null"]    # the file's run alone, not the fine-tuning it chains after it


@pytest.fixture(scope="module")
def curriculum_run(tmp_path_factory):
    """A clone of the scripted team (4 environments x 4 steps, one epoch), then three
    iterations of 4 environments x 2 steps on the evading task, a curriculum of three
    stages advanced every iteration, a checkpoint after each iteration; no final
    evaluation (``--no-eval``): the curriculum does not reach it, and tests/
    test_train_script.py runs one on the capture environment. ``(run folder, the
    script's result)``."""
    out = tmp_path_factory.mktemp("curriculum") / "run"
    env = {**os.environ, "JAX_LOG_COMPILES": "1"}
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), str(TRAIN_FILE), "--out", str(out),
                          "--no-progress", "--no-eval", *[a for s in CURRICULUM_RUN for a in ("--set", s)]],
                         capture_output=True, text=True, cwd=ROOT, env=env)
    assert res.returncode == 0, res.stderr
    return out, res


def test_train_script_runs_a_curriculum_and_logs_it(curriculum_run):
    """The stages and fractions logged per iteration, the change announced, the summary's
    first full-range iteration, the curves drawn."""
    out, res = curriculum_run
    # the stage changes give the compiled iterations new ranges inside the program (the
    # curriculum runs in it): the chunk of iterations is compiled once
    compiles = [ln for ln in res.stderr.splitlines() if "Compiling" in ln and "iterations" in ln]
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


def test_a_curriculum_run_resumes_from_its_checkpoint_alone(curriculum_run, tmp_path, capsys):
    """The run above cut back to its checkpoint of iteration 1, its metrics.csv deleted:
    resumed, it continues the curriculum at stage 2 (the checkpoint holds the stage and the
    episode ranges) and ends bit for bit where the uninterrupted run ended."""
    import shutil

    from conftest import run_script_main
    from mysim_jax.mappo.checkpoint import Checkpoints
    from mysim_jax.mappo.run import make_environment, prepare
    from mysim_jax.mappo.trainer import Trainer

    whole, _ = curriculum_run
    cut = tmp_path / "cut"
    shutil.copytree(whole, cut)
    for step in (2, 3):
        shutil.rmtree(cut / "checkpoints" / str(step))
        (cut / "checkpoints" / f"{step}.sha256.json").unlink()
    for name in ("metrics.csv", "summary.json"):
        (cut / name).unlink()
    shutil.rmtree(cut / "policy")
    code, out, err, _ = run_script_main("train", ["--resume", cut, "--no-eval", "--no-progress"], capsys)
    assert code == 0, err
    assert "resuming" in out and "at iteration 1 of 3" in out
    assert "curriculum: stage 2 of 3 (the target's speed, jink and flee ranges x 0.5)" in out
    assert "curriculum: stage 3 of 3 from iteration 3 (ranges x 1)" in out
    assert (cut / "policy" / "policy.msgpack").read_bytes() == (whole / "policy" / "policy.msgpack").read_bytes()
    # every leaf of the last checkpoint: networks, optimiser, environments, key, curriculum, ranges
    p = prepare(None, [], None, str(whole), None)
    env, env_params = make_environment(p)
    like = Trainer(p.config.algo, env, env_params).init(jax.random.PRNGKey(0))
    like = like.replace(curriculum=Curriculum(p.config.env.curriculum).start())     # the file's window
    states = []
    for run in (whole, cut):
        ckpt = Checkpoints(run / "checkpoints")
        states.append(ckpt.restore(3, like))
        ckpt.close()
    a, b = (jax.tree.leaves(s) for s in states)
    assert len(a) == len(b) and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(a, b))
    assert int(states[1].curriculum.stage) == 2 and int(states[1].iteration) == 3
    speeds = np.asarray(states[1].ranges.high.max_speed), np.asarray(env_params.ranges.high.max_speed)
    np.testing.assert_array_equal(*speeds)                  # the last stage draws from the full ranges


def test_a_checkpoint_of_an_earlier_state_layout_is_refused_and_kept(curriculum_run, tmp_path):
    """A checkpoint without the curriculum's fields (as an earlier version wrote them) is a
    clear error naming them; it is not taken for damage, so nothing is renamed."""
    import orbax.checkpoint as ocp
    from flax import serialization

    from mysim_jax.mappo.checkpoint import CheckpointError, Checkpoints
    from mysim_jax.mappo.run import make_environment, prepare
    from mysim_jax.mappo.trainer import Trainer

    whole, _ = curriculum_run
    p = prepare(None, [], None, str(whole), None)
    env, env_params = make_environment(p)
    state = Trainer(p.config.algo, env, env_params).init(jax.random.PRNGKey(0))
    old = {k: v for k, v in serialization.to_state_dict(state).items() if k not in ("curriculum", "ranges")}
    manager = ocp.CheckpointManager(tmp_path / "checkpoints", options=ocp.CheckpointManagerOptions(
        create=True, enable_async_checkpointing=False))
    manager.save(4, args=ocp.args.StandardSave(old), force=True)
    manager.wait_until_finished()
    manager.close()
    before = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    ckpt = Checkpoints(tmp_path / "checkpoints")
    with pytest.raises(CheckpointError, match=r"checkpoint 4 was written by an earlier version of mysim_jax "
                                              r"\(it has no curriculum, ranges\)"):
        ckpt.restore_newest(state, log=lambda _: None)
    ckpt.close()
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == before


def test_make_train_as_documented_trains_what_the_script_trains(curriculum_run):
    """docs/training.md's ``make_train`` example, run as written on the small run above
    (its ``load_run_config`` given the run's overrides): the cloning, the PPO iterations
    and the curriculum of ``train(PRNGKey(run.seed))`` end where ``scripts/train.py``
    ended. Not bit for bit: ``train`` is one compiled program and the script compiles the
    warm start and each chunk of iterations apart, so XLA orders float32 reductions
    differently; a few PPO steps on a tiny batch amplify that: measured 1.8e-5 at most in
    the parameters, asserted below 2e-4)."""
    import re

    from mysim_jax.mappo.checkpoint import Checkpoints

    whole, _ = curriculum_run
    text = (ROOT / "docs" / "training.md").read_text()
    # the first block (one seed); the vmapped seeds are tests/test_mappo.py's and
    # tests/test_train_script.py's, on the reach task (a vmapped capture run can hang on
    # this jaxlib's CPU backend: docs/training.md, "Known problem")
    example = re.search(r"```python\n(import jax\nfrom mysim_jax.mappo.algorithm import make_train.*?)```", text,
                        re.S).group(1)
    call = 'load_run_config("configs/train_capture_maneuvering.yaml")'
    assert call in example
    example = example.replace(call, f"load_run_config({str(TRAIN_FILE)!r}, {CURRICULUM_RUN!r})")
    scope: dict = {}
    exec(compile(example, "docs/training.md", "exec"), scope)
    state, metrics = scope["state"], scope["metrics"]
    assert int(state.iteration) == 3 and np.asarray(metrics["curriculum_stage"]).tolist() == [0, 1, 2]
    ckpt = Checkpoints(whole / "checkpoints")
    script = ckpt.restore(3, state)
    ckpt.close()
    worst = 0.0
    for a, b in zip(jax.tree.leaves(script.params), jax.tree.leaves(state.params)):
        worst = max(worst, float(np.max(np.abs(np.asarray(a) - np.asarray(b)))))
    assert worst < 2e-4, worst
    # the anchor is the clone: the same clone in both
    for a, b in zip(jax.tree.leaves(script.anchor), jax.tree.leaves(state.anchor)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2e-5)
    np.testing.assert_array_equal(np.asarray(script.curriculum.stage), np.asarray(state.curriculum.stage))
    print(f"make_train vs the script: max |parameter difference| {worst:.3g}")
