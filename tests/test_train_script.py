"""scripts/train.py: outputs, bad input, and a run killed with SIGKILL then resumed.

Runs on the builtin reach task (mysim_jax/mappo/toy.py), which compiles and trains in
seconds; the capture environment's path through the same code is tested once, tiny.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.config import reach_training_text

from conftest import only_array_ops, run_script_main

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train.py"

def reach_text(iterations: int, every: int) -> str:
    """The reach task's training file: ``iterations`` of 32 x 16 team steps, checkpoints
    every ``every``, 200 evaluation episodes."""
    return reach_training_text("reach_test", 32 * 16 * iterations, checkpoint_every=every, eval_episodes=200)


def _run(args, **kw):
    return subprocess.run([sys.executable, str(SCRIPT), *args, "--no-progress"], capture_output=True, text=True,
                          cwd=ROOT, **kw)


def _rows(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


TIMING = {"wall_s", "iteration_s"}


def test_outputs_and_learning(tmp_path):
    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_text(40, 10))
    out = tmp_path / "run"
    res = _run([str(cfg), "--out", str(out)])
    assert res.returncode == 0, res.stderr
    for name in ("train.yaml", "metrics.csv", "curves.png", "summary.json", "policy/policy.json",
                 "policy/policy.msgpack"):
        assert (out / name).is_file(), name
    assert any((out / "tb").iterdir())
    assert sorted(p.name for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == ["30", "40"]
    rows = _rows(out / "metrics.csv")
    assert [int(r["iteration"]) for r in rows] == list(range(1, 41))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 40 and summary["env_steps"] == 40 * 512
    # learning: the last iterations' episodes end in success far more often than the first
    assert summary["evaluation"]["success"]["rate"] > 0.8
    assert float(rows[1]["success_rate"]) < 0.3
    # it stopped on its step budget, and says so with the machine its wall times ran on
    assert summary["stopped_by"] == "step_budget" and not summary["stopped_by_time_limit"]
    assert summary["planned_env_steps"] == summary["env_steps"] == 40 * 512 and "cores" in summary["machine"]
    # the saved policy refuses an environment of another shape, naming both
    from mysim_jax.mappo.toy import ReachEnv
    from mysim_jax.mappo.policies import PolicyError, policy_maker

    with pytest.raises(PolicyError, match="trained on observations of size 8"):
        policy_maker(str(out / "policy"))(ReachEnv(n_agents=3), None)


def test_a_run_the_time_guard_stops_says_so(tmp_path):
    """run.time_limit_min is a guard: a run it stops before the step budget reports the
    stop and its iteration (summary.json), and the curve's title says so."""
    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_training_text("reach_guard", 32 * 16 * 200, checkpoint_every=50, eval_episodes=20,
                                       time_limit_min=0.0001))
    out = tmp_path / "run"
    res = _run([str(cfg), "--out", str(out)])
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "time_limit" and summary["stopped_by_time_limit"]
    assert summary["iterations"] < summary["planned_iterations"] == 200
    assert summary["env_steps"] == summary["iterations"] * 512 < summary["planned_env_steps"]
    assert f"time limit of 0.0001 min reached after iteration {summary['iterations']}" in res.stdout + res.stderr
    assert (out / "curves.png").is_file()


def test_the_curves_name_a_time_guard_stop(tmp_path, monkeypatch):
    import matplotlib.figure

    from mysim_jax.io.training_plots import plot_curves

    titles = []
    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle", lambda self, t, **k: titles.append(t))
    rows = [{"iteration": i, "env_steps": 512 * i, "episodes": 1, "mean_return": 0.1 * i, "success_rate": 0.1,
             "mean_length": 10, "value_loss": 1, "policy_loss": 0, "entropy": 1} for i in range(1, 4)]
    plot_curves(rows, tmp_path / "a.png", "t", None, (3, 200))
    plot_curves(rows, tmp_path / "b.png", "t", None, None)
    assert "stopped by the time guard (run.time_limit_min) after iteration 3 of 200" in titles[0]
    assert titles[1] == "t"


ITERATIONS, EVERY = 30, 5


@pytest.fixture(scope="module")
def whole_run(tmp_path_factory):
    """An uninterrupted reach run of 30 iterations, checkpointed every 5 (the last two
    kept: 25 and 30), without evaluation. Run first: the runs below then find the
    iteration's program in the compilation cache (a resumed run calls the program of a
    fresh start)."""
    tmp = tmp_path_factory.mktemp("whole")
    cfg = tmp / "reach.yaml"
    cfg.write_text(reach_text(ITERATIONS, EVERY))
    res = _run([str(cfg), "--out", str(tmp / "whole"), "--no-eval"])
    assert res.returncode == 0, res.stderr
    return cfg, tmp / "whole"


def test_sigkill_then_resume_equals_an_uninterrupted_run(tmp_path, whole_run):
    """Killed with SIGKILL once a checkpoint at iteration 10 or later exists, resumed: the policy
    and every iteration's metrics equal the uninterrupted run's exactly (bit for bit;
    tolerance 0), timing columns aside."""
    iterations = ITERATIONS
    cfg, whole = whole_run
    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, str(SCRIPT), str(cfg), "--out", str(killed), "--no-eval",
                             "--no-progress"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            steps = [int(p.name) for p in (killed / "checkpoints").glob("*") if p.name.isdigit()] \
                if (killed / "checkpoints").exists() else []
            if steps and max(steps) >= 10:
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the run ended before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:       # a failure above: do not leave it running
            proc.kill()
            proc.wait()
    done_at_kill = len(_rows(killed / "metrics.csv"))
    assert done_at_kill < iterations
    res = _run(["--resume", str(killed), "--no-eval"])
    assert res.returncode == 0, res.stderr
    assert "resuming" in res.stdout
    assert (killed / "policy" / "policy.msgpack").read_bytes() == (whole / "policy" / "policy.msgpack").read_bytes()
    a, b = _rows(whole / "metrics.csv"), _rows(killed / "metrics.csv")
    assert len(a) == len(b) == iterations
    for ra, rb in zip(a, b):
        assert {k: v for k, v in ra.items() if k not in TIMING} == {k: v for k, v in rb.items() if k not in TIMING}


def _damage(step_dir: Path, how: str) -> None:
    """Overwrite every data file of a checkpoint with random bytes, or empty them."""
    rng = np.random.default_rng(0)
    files = [f for f in step_dir.rglob("*") if f.is_file() and "d" in f.relative_to(step_dir).parts]
    assert files, step_dir
    for f in files:
        size = f.stat().st_size
        f.write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes() if how == "random" else b"")


def test_resume_skips_a_damaged_checkpoint_and_refuses_when_none_is_usable(tmp_path, whole_run):
    """The last checkpoint (30) damaged three ways; the one before (25) intact. Resuming
    takes 25 and says why 30 was skipped: its files differ from their checksums (random
    bytes), or, with the checksum file gone too, restoring it fails (emptied files). Through
    train.py the resumed run then ends with the uninterrupted run's policy, bit for bit.
    With both damaged, resuming is refused with one error naming the folder."""
    import shutil

    import jax

    from mysim_jax.mappo.checkpoint import CheckpointError, Checkpoints
    from mysim_jax.mappo.run import make_environment, prepare
    from mysim_jax.mappo.trainer import Trainer

    _, whole = whole_run
    assert sorted(p.name for p in (whole / "checkpoints").glob("*.sha256.json")) == ["25.sha256.json",
                                                                                      "30.sha256.json"]
    p = prepare(None, [], None, str(whole), None)
    env, env_params = make_environment(p)
    like = jax.eval_shape(Trainer(p.config.algo, env, env_params).init, jax.random.PRNGKey(0))
    for case in ("random", "empty, no checksum file", "both"):
        run = tmp_path / case.split(",")[0]
        shutil.copytree(whole, run)
        ckpt = run / "checkpoints"
        _damage(ckpt / "30", "random" if case == "random" else "empty")
        if case != "random":
            (ckpt / "30.sha256.json").unlink()
        if case == "both":
            _damage(ckpt / "25", "random")
        said = []
        checkpoints = Checkpoints(ckpt)
        if case == "both":
            with pytest.raises(CheckpointError, match=f"{ckpt}: none of the 2 checkpoints can be resumed from") as err:
                checkpoints.restore_newest(like, log=said.append)
            assert "checkpoint 30: restoring it failed" in str(err.value)
            assert "checkpoint 25: " in str(err.value) and "differ from their checksums" in str(err.value)
            continue
        step, state = checkpoints.restore_newest(like, log=said.append)
        assert step == 25 and int(state.iteration) == 25
        assert len(said) == 2 and said[0].startswith(f"skipping checkpoint 30 in {ckpt}: ")
        assert ("differ from their checksums" if case == "random" else "restoring it failed") in said[0]
        assert said[1] == f"moved the damaged checkpoint 30 to {ckpt / 'damaged-30'}"
        assert sorted(p.name for p in ckpt.iterdir() if p.is_dir()) == ["25", "damaged-30"]
    # through the script: the damaged run resumes from 25 and ends where the whole run ended
    shutil.rmtree(tmp_path / "random")
    shutil.copytree(whole, tmp_path / "random")
    _damage(tmp_path / "random" / "checkpoints" / "30", "random")
    res = _run(["--resume", str(tmp_path / "random"), "--no-eval"])
    assert res.returncode == 0, res.stderr
    assert "skipping checkpoint 30" in res.stdout and "resuming" in res.stdout
    assert (tmp_path / "random" / "policy" / "policy.msgpack").read_bytes() == \
        (whole / "policy" / "policy.msgpack").read_bytes()
    before = sorted(str(p.relative_to(tmp_path)) for p in (tmp_path / "both").rglob("*"))
    res = _run(["--resume", str(tmp_path / "both"), "--no-eval"])
    # exit 2 and one line: checkpoint 30 (no checksum file) is tried in a child process, so
    # orbax's abandoned reads print nothing here
    assert res.returncode == 2
    assert res.stderr.startswith(f"error: {tmp_path / 'both' / 'checkpoints'}: none of the 2 checkpoints")
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert sorted(str(p.relative_to(tmp_path)) for p in (tmp_path / "both").rglob("*")) == before


def test_a_run_starts_from_a_saved_policy(tmp_path, whole_run):
    """``algo.init: policy``: a reach run starts from the policy of ``whole_run``; with the
    critic warming up through every iteration and the observation normalisation frozen,
    the policy it saves is the one it started from, bit for bit (the exploration std aside,
    set to ``bc.std``). The run folder keeps a copy of the starting policy and its
    train.yaml points at it. A policy whose networks differ from the file's is refused
    before anything compiles."""
    from mysim_jax.mappo.checkpoint import load_policy
    from mysim_jax.mappo.run import prepare, train_run

    _, whole = whole_run
    cfg = tmp_path / "fine.yaml"
    raw = yaml.safe_load(reach_text(3, 3))
    raw["algo"].update(init="policy", init_policy=str(whole / "policy"),
                       bc={"std": 0.3, "critic_warmup": 10, "freeze_obs_norm": True})
    cfg.write_text(yaml.safe_dump(raw))
    out = tmp_path / "fine"
    summary = train_run(prepare(str(cfg), [], str(out)), progress=False, evaluate=False, log=lambda *a: None)
    assert summary["iterations"] == 3
    written = yaml.safe_load((out / "train.yaml").read_text())
    assert written["algo"]["init_policy"] == "init_policy" and (out / "init_policy" / "policy.json").is_file()
    (_, start), (_, end) = load_policy(whole / "policy"), load_policy(out / "policy")
    np.testing.assert_allclose(np.exp(end["actor"]["params"].pop("log_std")), 0.3, rtol=1e-6)
    start["actor"]["params"].pop("log_std")
    flat_start, flat_end = (jax.tree_util.tree_leaves_with_path(x) for x in (start, end))
    assert [k for k, _ in flat_start] == [k for k, _ in flat_end]
    for (k, a), (_, b) in zip(flat_start, flat_end):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(k))
    # another network width than the policy's: refused, naming both
    raw["algo"]["hidden"] = [64, 64]
    cfg.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"hidden \[128, 128\] there, \[64, 64\] here"):
        prepare(str(cfg), [], str(tmp_path / "other"))


def test_a_starting_policy_of_another_environment_is_refused_before_anything_is_written(tmp_path, capsys):
    """``algo.init: policy`` with the falling team's policy on the evading-drone scene: the
    shapes agree (52 observations, (4, 3) actions) but the policy.json records another
    scene, so the script exits 2 naming both, before the run folder is written (a second
    try is not told the folder holds a run) and before anything of the training compiles."""
    cfg = tmp_path / "t.yaml"
    cfg.write_text(f"name: t\nenv: {{scene: {ROOT / 'configs' / 'capture_env_maneuvering.yaml'}}}\n"
                   f"algo: {{init: policy, init_policy: {ROOT / 'docs' / 'train' / 'falling' / 'policy'}}}\n")
    out = tmp_path / "out"
    for _ in range(2):
        code, _, err, compiled = run_script_main("train", [cfg, "--out", out], capsys)
        assert code == 2, err
        assert "algo.init_policy" in err and "trained on another environment (capture_env_falling" in err, err
        assert "Traceback" not in err and only_array_ops(compiled)
        assert not out.exists()


@pytest.mark.parametrize("text, sets, message", [
    ("name: t\nenv: {builtin: reach}\nalgo: {num_envs: 10, num_steps: 3, num_minibatches: 4}\n", [],
     "num_minibatches"),
    ("name: t\nenv: {builtin: reach}\n", ["algo.lr=0"], "algo.lr"),
    ("name: t\nenv: {builtin: reach}\nalgo: {lr: -0.001}\n", [], "algo.lr"),
    ("name: t\nenv: {builtin: reach}\nalgo: {learnign_rate: 0.001}\n", [], "learnign_rate"),
    ("name: t\nenv: {scene: missing.yaml}\n", [], "env.scene: no such file"),
    ("name: t\nenv: {scene: ../configs/rope_net.yaml}\n", [], "not a capture environment"),
    ("name: t\nenv: {builtin: reach}\nrun: {checkpoint_every: 0}\n", [], "run.checkpoint_every"),
    ("name: t\nenv: {builtin: reach}\n", ["algo.batching=batch_first"],
     "algo.batching: Input should be 'auto', 'batch_last' or 'vmap'"),
    ("name: t\nenv: {builtin: reach}\nalgo: {init: policy, init_policy: nowhere}\n", [],
     "algo.init_policy nowhere: no saved policy there"),
    ("name: t\nenv: {builtin: reach}\nalgo: {init: policy}\n", [], "give its folder as init_policy"),
    ("name: t\nenv: {builtin: reach}\nalgo: {init_policy: somewhere}\n", [], "is used only with init: policy"),
    ("name: t\nenv: {builtin: reach}\nrun: {devices: 64}\n", [], "run.devices 64: JAX sees"),
    ("name: t\nenv: {builtin: reach}\nrun: {seeds: 2, devices: 2}\n", [], "run.seeds 2 with run.devices 2"),
    ("name: t\nenv: {builtin: reach}\nrun: {seeds: 0}\n", [], "run.seeds"),
    ("name: t\nenv: [1, 2]\n", [], "env"),
    ("name: t\nenv: {builtin: reach\n", [], "t.yaml"),
    ("name: t\nenv: {scene: ../configs/capture_env_falling.yaml, eval_level: trian}\n", [],
     "env.eval_level: ", ),
    ("name: t\nenv: {scene: ../configs/capture_env_falling.yaml, eval_scene: gone.yaml}\n", [],
     "give at most one of eval_level"),
    ("name: t\nenv: {scene: ../configs/capture_env_falling.yaml, eval_level: null, eval_scene: gone.yaml}\n", [],
     "env.eval_scene: no such file"),
    # networks far larger than any machine's memory (about 1.2 TB): refused before anything starts
    ("name: t\nenv: {builtin: reach}\n", ["algo.hidden=[200000, 200000]"], "algo.hidden [200000, 200000]"),
    # 2^24 capture environments x 64 steps: rollout buffers of about 3 TB, refused once the
    # environment's sizes are known and before the run folder is written or anything compiles
    ("name: t\nenv: {scene: ../configs/capture_env_falling.yaml}\nalgo: {num_envs: 16777216, num_steps: 64, "
     "num_minibatches: 4096, total_env_steps: 1073741824}\n", [], "lower algo.num_envs x algo.num_steps"),
])
def test_bad_configs_exit_2_before_compiling_and_write_nothing(tmp_path, capsys, text, sets, message):
    """The script's main() in this process (conftest.run_script_main): exit code 2, the
    message, nothing of the training compiled (conftest.only_array_ops), nothing written."""
    if "../configs" in text:
        text = text.replace("../configs", str(ROOT / "configs"))
    cfg = tmp_path / "t.yaml"
    cfg.write_text(text)
    out = tmp_path / "out"
    code, _, err, compiled = run_script_main("train", [cfg, "--out", out, *[a for s in sets for a in ("--set", s)]],
                                             capsys)
    assert code == 2
    assert message in err
    assert "Traceback" not in err
    assert only_array_ops(compiled)
    assert not out.exists()


def test_seeds_in_one_program_equal_separate_runs(tmp_path, capsys):
    """``--seeds 2``: seeds 1 and 2 of the reach task trained vmapped in one program, each
    in ``OUT/seed_<seed>/``, equal the runs of each seed alone (``--set run.seed=S``) to
    float32 round-off (vmap batches the matrix products differently, so not bit for bit):
    the same curves, the same policy; ``seeds.json`` / ``seeds.md`` table them."""
    from mysim_jax.mappo.checkpoint import load_policy

    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_text(8, 4))
    both = tmp_path / "both"
    code, out, err, _ = run_script_main("train", [cfg, "--seeds", "2", "--out", both, "--no-progress"], capsys)
    assert code == 0, err
    assert "seeds 1-2 in one program" in out
    assert sorted(p.name for p in both.iterdir()) == ["checkpoints", "curves.png", "seed_1", "seed_2", "seeds.json",
                                                      "seeds.md", "train.yaml"]
    worst = 0.0
    for seed in (1, 2):
        alone = tmp_path / f"alone_{seed}"
        code, _, err, _ = run_script_main("train", [cfg, "--set", f"run.seed={seed}", "--out", alone,
                                                    "--no-progress"], capsys)
        assert code == 0, err
        mine = both / f"seed_{seed}"
        a_rows, b_rows = _rows(mine / "metrics.csv"), _rows(alone / "metrics.csv")
        assert [r["iteration"] for r in a_rows] == [r["iteration"] for r in b_rows] == [str(i) for i in range(1, 9)]
        for key in ("mean_return", "success_rate", "policy_loss", "value_loss"):
            np.testing.assert_allclose([float(r[key]) for r in a_rows], [float(r[key]) for r in b_rows],
                                       rtol=1e-4, atol=1e-5, err_msg=key)
        (meta_a, arr_a), (meta_b, arr_b) = load_policy(mine / "policy"), load_policy(alone / "policy")
        assert meta_a["seed"] == meta_b["seed"] == seed
        for x, y in zip(jax.tree.leaves(arr_a), jax.tree.leaves(arr_b)):
            worst = max(worst, float(np.max(np.abs(np.asarray(x) - np.asarray(y)))))
        summary = json.loads((mine / "summary.json").read_text())
        assert summary["seed"] == seed and summary["seeds_in_program"] == 2 and summary["iterations"] == 8
    assert worst < 3e-6, worst          # measured 2.4e-7
    table = json.loads((both / "seeds.json").read_text())
    rates = [json.loads((both / f"seed_{s}" / "summary.json").read_text())["evaluation"]["success"]["rate"]
             for s in (1, 2)]
    assert table["seeds"] == [1, 2] and [r["success_rate"] for r in table["per_seed"]] == rates
    assert table["success_rate"]["mean"] == pytest.approx(np.mean(rates))
    assert table["success_rate"]["sd"] == pytest.approx(np.std(rates, ddof=1))
    assert "| 2 |" in (both / "seeds.md").read_text()
    print(f"vmapped seeds vs runs alone: max |policy parameter difference| {worst:.3g}")


def test_the_process_flags_go_together(tmp_path, capsys):
    """--coordinator, --num-processes and --process-id: all three or none, and an id in
    range; refused before anything starts."""
    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_text(2, 1))
    for flags, message in ((["--coordinator", "127.0.0.1:1234"], "go together"),
                           (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "2"],
                            "--process-id 2 with --num-processes 2")):
        code, _, err, compiled = run_script_main("train", [cfg, "--out", tmp_path / "out", *flags], capsys)
        assert code == 2 and message in err and "Traceback" not in err and only_array_ops(compiled)
        assert not (tmp_path / "out").exists()


def test_an_existing_run_is_not_overwritten(tmp_path, capsys):
    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_text(2, 1))
    out = tmp_path / "run"
    out.mkdir()
    (out / "train.yaml").write_text("name: x\n")
    code, _, err, compiled = run_script_main("train", [cfg, "--out", out], capsys)
    assert code == 2 and "--resume" in err and only_array_ops(compiled)
    code, _, err, _ = run_script_main("train", ["--resume", tmp_path / "nothing"], capsys)
    assert code == 2 and "not a training run folder" in err


def test_capture_environment_end_to_end_tiny(tmp_path):
    """The default training file's path on the capture environment, tiny: behaviour cloning
    from 32 environments x 16 steps (the demonstration program of tests/test_bc.py, which
    then comes from the compilation cache), one iteration of 4 environments x 2 steps, model
    selection on 2 episodes before and after it, all on the level ``train``; the final
    evaluation (2 episodes, no baseline; a batch of 4 asked for, 2 run) on the level ``full``; the saved policy then loads
    as evaluate.py's --policy RUN/policy and is traced on the environment (jax.eval_shape,
    no compile)."""
    out = tmp_path / "run"
    sets = ["algo.num_envs=4", "algo.num_steps=2", "algo.total_env_steps=8", "algo.num_minibatches=2",
            "algo.bc.num_envs=32", "algo.bc.steps=16", "algo.bc.epochs=2", "algo.bc.holdout=0.2",
            "run.selection.episodes=2", "run.selection.every=1", "env.eval_level=full",
            "run.eval_episodes=2", "run.eval_batch=4", "run.eval_baseline=false", "env.level=train",
            "run.then=null"]
    res = _run(["configs/train_capture_falling.yaml", "--out", str(out), *[a for s in sets for a in ("--set", s)]])
    assert res.returncode == 0, res.stderr
    # a batch larger than the episodes is not an error, but it is said
    assert "note: run.eval_batch 4 is more than run.eval_episodes 2: the final evaluation runs 2 side by side" \
        in res.stdout
    # the run folder is self-contained: its scene is the resolved training scene (velocity
    # setpoints, the scene's own discount, the level train), and the
    # evaluation's scene is the level full with the same overrides
    scene_text = (out / "scene.yaml").read_text()
    assert "setpoint_mode: velocity" in scene_text and "discount: 0.99" in scene_text and "level: train" in scene_text
    from mysim_jax.config.scene import load_config

    trained_on, evaluated_on = load_config(out / "scene.yaml"), load_config(out / "scene_eval.yaml")
    assert trained_on.level == "train" and trained_on.net.masses_per_edge == 0
    assert evaluated_on.level == "full" and evaluated_on.net.masses_per_edge == 1
    assert evaluated_on.env.discount == trained_on.env.discount
    assert evaluated_on.quadrotors[0].controller == trained_on.quadrotors[0].controller
    run_file = yaml.safe_load((out / "train.yaml").read_text())
    assert run_file["env"]["eval_scene"] == "scene_eval.yaml" and run_file["env"]["eval_level"] is None
    summary = json.loads((out / "summary.json").read_text())
    assert not (out / ".eval.resume").exists()      # the evaluation's progress is removed once written
    assert summary["training_level"] == "train" and summary["evaluation"]["level"] == "full"
    assert summary["evaluation"]["episodes"] == 2
    assert yaml.safe_load((out / "eval" / "config.yaml").read_text())["level"] == "full"
    assert summary["iterations"] == 1 and summary["env_steps"] == 8 and summary["init"] == "bc"
    bc = json.loads((out / "bc.json").read_text())
    assert bc["pairs"] == 32 * 16 * 4 and bc["holdout_environments"] == 6
    assert summary["behaviour_cloning"] == bc
    assert summary["selection"]["selected_iteration"] in (0, 1) and summary["selection"]["episodes"] == 2
    assert summary["selection"]["scene"] == "training" and not (out / "scene_select.yaml").exists()
    # iteration 0 is the clone's selection row; the policy saved is the selected one
    rows = _rows(out / "metrics.csv")
    assert [int(r["iteration"]) for r in rows] == [0, 1]
    assert rows[0]["select_success"] != "" and rows[1]["select_success"] != ""
    assert all(v != "nan" for v in rows[1].values())
    assert json.loads((out / "policy" / "policy.json").read_text())["selected_iteration"] == \
        summary["selection"]["selected_iteration"]

    from mysim_jax.tasks.capture import make_env
    from mysim_jax.mappo.policies import check_policy, policy_maker

    env, params = make_env(evaluated_on)
    policy = policy_maker(str(out / "policy"))(env, params)
    check_policy(env, params, policy, str(out / "policy"))


def test_policy_folders_are_checked(tmp_path):
    from mysim_jax.mappo.policies import PolicyError, check_policy_spec, policy_maker

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PolicyError, match="without policy.json"):
        check_policy_spec(str(empty))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "policy.json").write_text("{not json")
    (bad / "policy.msgpack").write_bytes(b"\x00")
    with pytest.raises(PolicyError, match="cannot read the saved policy"):
        policy_maker(str(bad))


def test_runs_side_by_side_plot_reads_every_run(tmp_path):
    """plot_runs draws one line per run from metrics.csv rows (selection and training
    success against wall time); a run without selection rows still gets its training line."""
    import matplotlib

    matplotlib.use("Agg")
    from mysim_jax.io.training_plots import plot_runs
    from mysim_jax.mappo.run_files import CSV_FIELDS, read_metrics, write_rows

    runs = {}
    for name, selection in (("with_selection", True), ("without", False)):
        folder = tmp_path / name
        folder.mkdir()
        rows = [{"iteration": i, "wall_s": 60.0 * i, "episodes": 4, "success_rate": 0.25 * i,
                 "select_success": (0.5 if selection and i % 2 == 0 else "")} for i in range(5)]
        write_rows(folder / "metrics.csv", rows)
        runs[name] = read_metrics(folder)
        assert [int(r["iteration"]) for r in runs[name]] == list(range(5))
        assert set(runs[name][0]) == set(CSV_FIELDS)
    out = plot_runs(runs, tmp_path / "runs.png", "two runs")
    assert out.is_file() and out.stat().st_size > 10_000
    assert plot_runs({}, tmp_path / "none.png", "no runs") is None


def test_a_run_stopped_in_its_final_evaluation_resumes_there(tmp_path, capsys, monkeypatch):
    """The capture path, tiny (the sets of the test above, 6 evaluation episodes with the
    scripted team beside them): a run whose final evaluation is stopped after its first
    saved progress resumes (``--resume``) inside that evaluation, not from its first
    episode, and ends with exactly the outcomes of a run that was not stopped."""
    import mysim_jax.mappo.run_outputs as run_outputs
    from mysim_jax.tasks.evaluate import Checkpoint

    sets = ["algo.num_envs=4", "algo.num_steps=2", "algo.total_env_steps=8", "algo.num_minibatches=2",
            "algo.bc.num_envs=32", "algo.bc.steps=16", "algo.bc.epochs=2", "algo.bc.holdout=0.2",
            "run.selection.episodes=2", "run.selection.every=1", "run.eval_episodes=6", "run.eval_batch=2",
            "run.eval_baseline=true", "env.level=train", "env.eval_level=null", "run.then=null"]
    args = ["configs/train_capture_falling.yaml", *[a for s in sets for a in ("--set", s)], "--no-progress"]
    code, _, err, _ = run_script_main("train", [*args, "--out", tmp_path / "whole"], capsys)
    assert code == 0, err

    class Stopped(RuntimeError):
        pass

    saves = []

    class StopAfterFirstSave(Checkpoint):
        def __init__(self, path, fingerprint="", every_s=300.0):
            super().__init__(path, fingerprint, 0.0)          # saved after every call

        def save(self, *a, **k):
            super().save(*a, **k)
            saves.append(self.path)
            raise Stopped

    monkeypatch.setattr(run_outputs, "Checkpoint", StopAfterFirstSave)
    with pytest.raises(Stopped):
        run_script_main("train", [*args, "--out", tmp_path / "stopped"], capsys)
    assert len(saves) == 1 and saves[0].exists() and saves[0].parent.name == ".eval.resume"
    with np.load(saves[0]) as z:
        assert 0 <= z["episodes"].size < 6                  # stopped inside the evaluation
    monkeypatch.undo()

    calls = []
    real_load = Checkpoint.load

    def load(self, meta, carry):
        found = real_load(self, meta, carry)
        calls.append(found is not None)
        return found

    monkeypatch.setattr(Checkpoint, "load", load)
    code, _, err, _ = run_script_main("train", ["--resume", tmp_path / "stopped", "--no-progress"], capsys)
    assert code == 0, err
    assert calls[0] is True                                  # the learned team's evaluation went on
    assert not (tmp_path / "stopped" / ".eval.resume").exists()
    for name in ("episodes.csv", "comparison_episodes.csv"):
        assert (tmp_path / "stopped" / "eval" / name).read_text() == (tmp_path / "whole" / "eval" / name).read_text()
