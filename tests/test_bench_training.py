"""The training-runs list of BENCHMARKS.md (g) (mysim_jax/bench/training.py), written from kept
run folders like those in docs/train/: a row per run, the paired difference to the scripted
team (the run's own, or from another run's scripted outcomes on the same episodes), the
spread over seeds, and a run stopped before its evaluation. The folders here are made up;
nothing is trained."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import yaml

from mysim_jax.bench import training
from mysim_jax.config.scene import dump_config, load_config
from mysim_jax.tasks.sweep import paired_difference_interval

METRICS = ("iteration", "env_steps", "wall_s", "episodes", "success_rate", "select_success")
SCENE = Path(__file__).resolve().parents[1] / "configs" / "capture_env_falling.yaml"
FALLING = dump_config(load_config(SCENE))
# the same scene name, another allocation: the scripted team flies other episodes' outcomes
ATTITUDE = dump_config(load_config(SCENE, [f"quadrotors.{i}.controller.saturation=attitude_priority"
                                           for i in range(4)]))
ONE_UAV_ATTITUDE = dump_config(load_config(SCENE, ["quadrotors.0.controller.saturation=attitude_priority"]))


def _run(folder, name: str, seed: int, metrics, summary=None, episodes=None, scripted=None, scene=FALLING,
         **more):
    run = folder / name
    (run / "eval").mkdir(parents=True)
    (run / "train.yaml").write_text(yaml.safe_dump({"run": {"seed": seed, "eval_seed": 7, **more.get("run", {})},
                                                    "algo": {"init": "bc", **more.get("algo", {})},
                                                    **{k: v for k, v in more.items() if k not in ("run", "algo")}}))
    (run / "scene.yaml").write_text(scene)
    with (run / "metrics.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(METRICS)
        w.writerows(metrics)
    if summary is not None:
        (run / "summary.json").write_text(json.dumps(summary))
    if episodes is not None:
        (run / "eval" / "episodes.csv").write_text("episode,success\n" + "".join(
            f"{i},{int(s)}\n" for i, s in enumerate(episodes)))
    if scripted is not None:
        (run / "eval" / "comparison_episodes.csv").write_text("episode,outcome_scripted\n" + "".join(
            f"{i},{'success' if s else 'target_ground'}\n" for i, s in enumerate(scripted)))


def _summary(rate: float, **more) -> dict:
    return {"env_steps": 1024, "training_wall_s_total": 120.0, "evaluation_wall_s": 60.0,
            "env_steps_per_s_with_update": 50.0,
            "evaluation": {"episodes": 4, "success": {"rate": rate, "interval95": [0.25, 0.95]},
                           "failures": {"target_ground": {"count": 1}, "uav_ground": {"count": 0}}}, **more}


def test_the_runs_list_pairs_runs_with_the_scripted_team_and_groups_seeds(tmp_path):
    rows = [(0, 0, 10.0, "", "", "0.25"), (1, 1024, 120.0, "4", "0.5", "")]
    scripted = [True, True, False, True]
    _run(tmp_path, "a_seed0", 0, rows, scripted=scripted, summary=_summary(
        0.75, stopped_by_time_limit=True,
        baseline={"seed": 7, "difference": {"estimate": 0.01, "interval95": [-0.02, 0.04]}}))
    # seed 1 of the same file: its scripted team not run beside it, the file grown a profile
    # and a field left unset (null)
    _run(tmp_path, "a_seed1", 1, rows, summary=_summary(0.5, machine="CPU X (family 1), 2 cores"),
         episodes=[True, False, True, False], run={"eval_baseline": False}, profiles={"p": ["algo.lr=1"]},
         algo={"init_policy": None})
    # another learning rate: not a seed of the same settings; two runs of one seed with the
    # same settings (other code): not seeds of one experiment
    _run(tmp_path, "a_other_lr", 2, rows, summary=_summary(0.25), algo={"lr": 0.5})
    _run(tmp_path, "d_code_a", 3, rows, summary=_summary(0.25), algo={"lr": 0.7})
    _run(tmp_path, "d_code_b", 3, rows, summary=_summary(0.5), algo={"lr": 0.7})
    _run(tmp_path, "b_stopped", 0, rows)
    no_eval = _summary(0.5)
    for key in ("evaluation", "evaluation_wall_s"):
        no_eval.pop(key)
    _run(tmp_path, "c_no_eval", 0, rows, summary=no_eval)
    (tmp_path / "machines.yaml").write_text("b_stopped: an older machine\n")
    (tmp_path / "b_stopped" / "NOTE.md").write_text("Stopped by hand.\n")
    lines = training.training_runs_lines(tmp_path)

    assert lines[0] == "### Training runs"
    table = [ln for ln in lines if ln.startswith("| `")]
    assert [ln.split("`")[1] for ln in table] == ["a_other_lr", "a_seed0", "a_seed1", "b_stopped", "c_no_eval",
                                                      "d_code_a", "d_code_b"]
    table = table[1:]
    # the machine: the summary's, else machines.yaml's entry, else not recorded
    assert table[0] == ("| `a_seed0` | bc | 0 | 1,024 (stopped by the time guard) | not recorded | 2.0 | 50 | 1.0 | "
                        "**75.0%** (25.0%–95.0%) of 4 | +1.0 (-2.0 to +4.0) | 1 target_ground |")
    assert "| 1,024 | CPU X (family 1), 2 cores | 2.0 |" in table[1]
    d, lo, hi = paired_difference_interval([True, False, True, False], scripted)
    assert f"| {100 * d:+.1f} ({100 * lo:+.1f} to {100 * hi:+.1f}) |" in table[1]
    assert table[2] == ("| `b_stopped` | bc | 0 | 1,024 | an older machine | 2.0 | — | — | not evaluated (stopped "
                        "after training); "
                        "selection success 25% at 0 | — | — |")
    # trained with --no-eval: a summary without an evaluation
    assert table[3] == ("| `c_no_eval` | bc | 0 | 1,024 | not recorded | 2.0 | 50 | — | not evaluated (trained "
                        "with --no-eval); selection success 25% at 0 | — | — |")
    [seeds] = [ln for ln in lines if ln.startswith("**Over seeds**")]
    assert "(`a_seed0`, `a_seed1`: the same file and settings" in seeds and "mean **62.5%**" in seeds
    assert "![kept training runs side by side](docs/train/runs.png)" in lines
    assert (tmp_path / "runs.png").is_file()
    assert lines[-2:] == ["**b_stopped**: Stopped by hand.", ""]


def test_a_chains_second_run_is_listed_and_pairs_only_on_the_scene_it_flew(tmp_path):
    """A kept chain's second run (``<run>/then/``) has a row of its own. Runs pair with the
    scripted outcomes of a run evaluated on the same scene as today's schema reads it
    (an older dump without a field added since pairs; the description and level table
    do not count), not on a scene of the same name that differs (the allocation)."""
    rows = [(0, 0, 10.0, "", "", "0.25"), (1, 1024, 120.0, "4", "0.5", "")]
    base = {"seed": 7, "difference": {"estimate": 0.0, "interval95": [0.0, 0.0]}}
    clip_scripted, attitude_scripted = [True, True, True, False], [False, True, False, False]
    _run(tmp_path, "a_clip", 0, rows, summary=_summary(0.75, baseline=base), scripted=clip_scripted)
    _run(tmp_path, "b_attitude", 0, rows, summary=_summary(0.75, baseline=base), scripted=attitude_scripted,
         scene=ATTITUDE)
    older = yaml.safe_load(FALLING)
    older["description"] = "the same scene, described and dumped by older code"
    older["levels"]["train"].pop("resolved")
    older["levels"]["train"]["description"] = "the cheap level as older code described it"
    _run(tmp_path, "c_older_dump", 1, rows, summary=_summary(0.5), episodes=[True, False, False, True],
         scene=yaml.safe_dump(older))
    _run(tmp_path, "d_chain", 2, rows, summary=_summary(0.5), episodes=[True, True, False, False])
    _run(tmp_path / "d_chain", "then", 2, rows, summary=_summary(0.5), episodes=[True, True, True, False],
         scene=ATTITUDE)
    _run(tmp_path, "e_unpaired", 3, rows, summary=_summary(0.5), episodes=[True, False, True, False],
         scene=ONE_UAV_ATTITUDE)
    table = {ln.split("`")[1]: ln for ln in training.training_runs_lines(tmp_path) if ln.startswith("| `")}
    assert list(table) == ["a_clip", "b_attitude", "c_older_dump", "d_chain", "d_chain/then", "e_unpaired"]

    def versus(mine, scripted):
        d, lo, hi = paired_difference_interval(mine, scripted)
        return f"| {100 * d:+.1f} ({100 * lo:+.1f} to {100 * hi:+.1f}) |"

    assert versus([True, False, False, True], clip_scripted) in table["c_older_dump"]
    assert versus([True, True, False, False], clip_scripted) in table["d_chain"]
    assert versus([True, True, True, False], attitude_scripted) in table["d_chain/then"]
    assert "| — | 1 target_ground |" in table["e_unpaired"]                 # no scripted run on its scene


def test_no_kept_runs_give_no_list(tmp_path):
    (tmp_path / "not_a_run").mkdir()
    assert training.training_runs_lines(tmp_path) == []


def test_the_seeds_of_a_chain_are_grouped_run_by_run(tmp_path):
    """Three seeds of a chain (the first runs naming their second, ``then/``, which starts
    from ``../policy``): the first runs are one group of seeds and the second runs another,
    each with its spread; the first runs' scripted outcomes pair with the second runs that
    flew the same scene."""
    rows = [(0, 0, 10.0, "", "", "0.25"), (1, 1024, 120.0, "4", "0.5", "")]
    scripted = [True, True, False, True]
    base = {"seed": 7, "difference": {"estimate": 0.0, "interval95": [0.0, 0.0]}}
    for seed, (first, second) in enumerate([(0.5, 0.75), (0.25, 0.75), (0.5, 1.0)]):
        name = f"chain_seed{seed}"
        _run(tmp_path, name, seed, rows, summary=_summary(first, **({"baseline": base} if seed == 0 else {})),
             scripted=scripted if seed == 0 else None, episodes=[True, False, True, False],
             run={"then": "then/train.yaml", "eval_baseline": seed == 0})
        _run(tmp_path / name, "then", seed, rows, summary=_summary(second), episodes=[True, True, True, False],
             run={"eval_baseline": False}, algo={"init": "policy", "init_policy": "../policy"})
    lines = training.training_runs_lines(tmp_path)
    seeds = [ln for ln in lines if ln.startswith("**Over seeds**")]
    assert len(seeds) == 2
    first, second = sorted(seeds, key=lambda ln: "/then" in ln)
    assert "(`chain_seed0`, `chain_seed1`, `chain_seed2`:" in first and "mean **41.7%**" in first
    assert "(`chain_seed0/then`, `chain_seed1/then`, `chain_seed2/then`:" in second and "mean **83.3%**" in second
    table = {ln.split("`")[1]: ln for ln in lines if ln.startswith("| `")}
    d, lo, hi = paired_difference_interval([True, True, True, False], scripted)
    assert all(f"| {100 * d:+.1f} ({100 * lo:+.1f} to {100 * hi:+.1f}) |" in table[f"chain_seed{s}/then"]
               for s in range(3))
