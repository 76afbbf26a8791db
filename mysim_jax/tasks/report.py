"""The evaluation report of a capture team: what ``scripts/evaluate.py`` writes, and what
``scripts/train.py`` writes for its trained policy at the end of a run.

:func:`write_evaluation` runs the episodes (:func:`~mysim_jax.tasks.evaluate.run_episodes`),
replays slot 0's first episode, and writes into ``out`` (through
:func:`~mysim_jax.io.output.staged_output`: all files or none):

* ``metrics.json`` — rates with 95 % Wilson intervals, mean terms, return and length,
  wall time; the config, policy, episodes, batch, seed; the recorded episode's outcome;
* ``episodes.csv`` — one row per episode;
* ``outcomes.png``, ``reward_terms.png``, ``lengths.png``, ``returns.png``;
* ``config.yaml``, ``trajectory.csv``, ``episode_steps.csv``, ``episode_rewards.png`` and
  the ``capture_*.png`` plots (and ``capture.gif`` with ``animate``) of the replayed episode.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import jax
import numpy as np

from mysim_jax.config.scene import dump_config
from mysim_jax.io.eval_plots import episode_columns, evaluation_plots, outcome_labels, plot_episode_rewards
from mysim_jax.io.output import staged_output
from mysim_jax.io.trajectory import write_trajectory_csv
from mysim_jax.tasks.capture_plots import capture_report
from mysim_jax.tasks.episode import record_columns, record_episode, step_columns
from mysim_jax.tasks.evaluate import run_episodes
from mysim_jax.tasks.sweep import paired_difference_interval


def write_evaluation(out: Path, config, env, params, policy, *, policy_name: str, episodes: int, batch: int,
                     seed: int, config_path: str, overrides=(), env_note: str | None = None,
                     progress: bool = True, animate: bool = True, extra: dict | None = None,
                     stats=None) -> dict:
    """Evaluate ``policy`` on ``episodes`` episodes and write the report into ``out``.
    Returns the ``metrics.json`` dict. ``stats``: the episodes' EpisodeStats when they
    have been run already (episodes ``0 .. episodes − 1`` of ``seed``)."""
    key = jax.random.PRNGKey(seed)
    batch = min(batch, episodes)
    if stats is None:
        stats = run_episodes(env, params, policy, episodes, batch, key, progress=progress)
    # episode 0, replayed with its key
    record = record_episode(env, params, policy, key, 0)

    summary = stats.summary()
    first = 0
    with staged_output(out) as tmp:
        (tmp / "config.yaml").write_text(dump_config(config))
        write_trajectory_csv(tmp / "episodes.csv", episode_columns(stats, env.policy_dt))
        plots = [p.name for p in evaluation_plots(stats, tmp, env.policy_dt, config.name)]
        columns = record_columns(env, record)
        write_trajectory_csv(tmp / "trajectory.csv", columns)
        steps = step_columns(env, record)
        write_trajectory_csv(tmp / "episode_steps.csv", steps)
        plots.append(plot_episode_rewards(steps, tmp / "episode_rewards.png", config.name).name)
        capture = capture_report(columns, env.scene, record.sim_params, config, tmp, animate=animate)
        plots += capture["plots"]
        metrics = {
            "scene": config.name,
            "config": str(config_path),
            "overrides": list(overrides),
            "env_block": "defaults" if env_note else "file",
            "policy": policy_name,
            "episodes": episodes,
            "batch": batch,
            "seed": seed,
            "policy_dt": env.policy_dt,
            "max_steps": env.max_steps,
            **summary,
            "recorded_episode": {
                "episode": 0, "outcome": record.outcome, "length_steps": record.length,
                "length_s": float(record.trajectory.time[-1]), "mean_return": float(record.returns.mean()),
                # the same episode in the batched run: identical draws, but after a contact the
                # two compiled runs can drift apart and end differently
                "evaluated_outcome": str(outcome_labels(stats)[first]),
                "evaluated_length_steps": int(stats.length[first]),
                "capture": capture,
            },
            "plots": plots,
            **(extra or {}),
        }
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def summary_line(name: str, policy_name: str, metrics: dict, out) -> str:
    """One line for the terminal: success with its interval, timeouts, failures, return."""
    s = metrics["success"]
    failures = ", ".join(f"{k.replace('_', ' ')} {v['rate']:.0%}" for k, v in metrics["failures"].items()
                         if v["count"])
    return (f"{name}: {metrics['episodes']} episodes of policy '{policy_name}' in {metrics['wall_s']:.1f} s "
            f"(compile included): success {s['rate']:.1%} (95 % {s['interval95'][0]:.1%}-{s['interval95'][1]:.1%}), "
            f"timeout {metrics['timeout']['rate']:.1%}" + (f", failures: {failures}" if failures else "")
            + f"; mean return {metrics['mean_return']:.3g}; wrote {out}/ ({len(metrics['plots'])} plots)")


def compare(a, b, names=("a", "b")) -> dict:
    """Two teams' outcomes on the same episodes (``a``, ``b``: EpisodeStats of episodes
    ``0 .. n − 1`` of one seed): both success rates with their Wilson intervals, the
    paired difference ``a − b`` with its 95 % interval
    (:func:`~mysim_jax.tasks.sweep.paired_difference_interval`), and the episode counts
    where only one of them succeeded."""
    if a.n != b.n:
        raise ValueError(f"compare: {a.n} and {b.n} episodes; a paired comparison needs the same episodes")
    d, lo, hi = paired_difference_interval(a.success, b.success)
    return {
        "episodes": a.n,
        "teams": list(names),
        "success": {names[0]: a.rate(a.success), names[1]: b.rate(b.success)},
        "difference": {"estimate": d, "interval95": [lo, hi], "of": f"{names[0]} - {names[1]}"},
        "only_" + names[0]: int(np.sum(a.success & ~b.success)),
        "only_" + names[1]: int(np.sum(b.success & ~a.success)),
        "both": int(np.sum(a.success & b.success)),
        "neither": int(np.sum(~a.success & ~b.success)),
        "mean_length_steps": {names[0]: float(np.mean(a.length)), names[1]: float(np.mean(b.length))},
        "failures": {names[0]: {k: int(v.sum()) for k, v in a.failures.items() if v.any()},
                     names[1]: {k: int(v.sum()) for k, v in b.failures.items() if v.any()}},
    }


def write_comparison(out: Path, a, b, *, names=("a", "b"), seed: int | None = None, extra: dict | None = None
                     ) -> dict:
    """Write ``comparison.json`` and ``comparison_episodes.csv`` (per episode, each team's
    outcome and length) into the existing folder ``out``; returns the comparison
    (:func:`compare`)."""
    out = Path(out)
    result = {**compare(a, b, names), "seed": seed, **(extra or {})}
    (out / "comparison.json").write_text(json.dumps(result, indent=2))
    la, lb = outcome_labels(a), outcome_labels(b)
    with (out / "comparison_episodes.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", f"outcome_{names[0]}", f"outcome_{names[1]}", f"length_{names[0]}",
                    f"length_{names[1]}"])
        for i in range(a.n):
            w.writerow([i, la[i], lb[i], int(a.length[i]), int(b.length[i])])
    return result


def comparison_line(result: dict) -> str:
    """One line: both success rates and the paired difference with its interval."""
    a, b = result["teams"]
    d = result["difference"]
    sa, sb = result["success"][a], result["success"][b]
    return (f"{a} {sa['rate']:.1%} vs {b} {sb['rate']:.1%} on the same {result['episodes']} episodes: difference "
            f"{100 * d['estimate']:+.1f} points (95 % {100 * d['interval95'][0]:+.1f} to "
            f"{100 * d['interval95'][1]:+.1f}); only {a} caught {result['only_' + a]}, only {b} {result['only_' + b]}")
