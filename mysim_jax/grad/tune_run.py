"""Tune a capture scene's scripted team and write the run (``scripts/tune.py``; the
problem is :mod:`.tune`).

Into a folder:

* ``tune.json`` — the settings, the objective's weights, the machine, the wall times,
  the box, the history, the best ``v`` and value, the nominal value on the same
  episodes, the tuned fields and the ``team:`` values to paste into the scene;
* ``history.csv`` — the history (one row per gradient step, generation or batch);
* ``tune_best.png`` — the best value against the team steps spent;
* ``judged.json`` (unless no judging episodes) — the tuned and the configured team on the
  same fresh episodes at the judging level, with the capture verdict: both success
  rates with Wilson intervals, the paired difference with its interval.

:func:`run_design` writes the same files for a design tuning (:mod:`.design`): in
``tune.json`` the designed keys, their bounds, the best values and the ``--set`` entries
that give the tuned scene (the tethered UAVs' moved starts included); the value is the
miss rate on the fixed episodes.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from mysim_jax.core.machine import cpu_model, usable_cores  # noqa: E402
from mysim_jax.grad.design import DesignProblem, design_overrides, judge_design, tune_design  # noqa: E402
from mysim_jax.grad.gradmap_run import csv_text  # noqa: E402
from mysim_jax.grad.objective import ObjectiveWeights  # noqa: E402
from mysim_jax.grad.tune import TuningProblem, judge, team_block, tune, tuned_fields  # noqa: E402
from mysim_jax.io.output import staged_output  # noqa: E402
from mysim_jax.tasks.capture import make_env  # noqa: E402

HISTORY_COLUMNS = ("evaluations", "team_steps", "value", "best", "wall_s")


def run_tune(config, settings: dict, out_dir: Path, judge_config=None, weights: ObjectiveWeights = ObjectiveWeights(),
             progress: bool = True, log=print) -> dict:
    """Tune ``config``'s team (a capture scene at the tuning level) with ``settings``
    (``method``, ``budget``, ``episodes``, ``horizon`` in policy steps or None,
    ``seed``, ``truncate``, ``batch``, ``box``, ``judge_episodes``, ``judge_seed``,
    ``judge_batch``; the rest recorded as given), judge it on ``judge_config`` (the scene
    at the judging level; None: not judged) and write the folder (module docstring).
    Returns the tuning's JSON dict."""
    t0 = time.perf_counter()
    env, params = make_env(config)
    problem = TuningProblem(env, params, weights, episodes=settings["episodes"], horizon=settings["horizon"],
                            seed=settings["seed"], box=settings["box"], truncate=settings["truncate"])
    with tqdm(total=int(settings["budget"]), desc=f"tune ({settings['method']})", unit="team step",
              disable=not progress) as bar:
        result = tune(problem, settings["method"], settings["budget"], batch=settings["batch"],
                      seed=settings["seed"], progress=bar.update)
    # the configured team's value on the same episodes (gradient descent starts there)
    nominal = (result.history[0]["value"] if settings["method"] == "grad"
               else float(problem.evaluate(np.zeros((1, problem.size)))[0]))
    policy = config.team.policy if config.team is not None else "scripted"
    out = {"config": settings.get("config"), "settings": settings, "weights": dataclasses.asdict(weights),
           "machine": {"cpu": cpu_model(), "cores": usable_cores()}, "team": type(env.scripted).__name__,
           "fields": list(problem.names), "nominal_fields": dict(zip(problem.names, problem.nominal.tolist())),
           "box": {"lower": problem.lower.tolist(), "upper": problem.upper.tolist()},
           "steps_per_evaluation": problem.steps_per_evaluation, "team_steps": result.team_steps,
           "nominal_value_m": nominal, "best_value_m": result.best_value, "best_u": result.best_u.tolist(),
           "tuned_fields": tuned_fields(problem, result.best_u), "team_block": team_block(problem, result.best_u, policy),
           "history": result.history, "tune_wall_s": time.perf_counter() - t0}
    judged = None
    if judge_config is not None and settings["judge_episodes"] > 0:
        jenv, jparams = make_env(judge_config)
        judged = judge(problem, result.best_u, jenv, jparams, settings["judge_episodes"], settings["judge_batch"],
                       settings["judge_seed"], progress=progress)
        judged.update(level=settings["judge_level"], tuned_fields=out["tuned_fields"])
    out["wall_s"] = time.perf_counter() - t0
    with staged_output(out_dir) as folder:
        (folder / "tune.json").write_text(json.dumps(out, indent=2))
        (folder / "history.csv").write_text(history_csv(result.history))
        plot_best(result.history, nominal, folder / "tune_best.png", f"{settings['method']}: {settings.get('config')}")
        if judged is not None:
            (folder / "judged.json").write_text(json.dumps(judged, indent=2))
    log(summary(out, judged, out_dir))
    return out


def run_design(problem: DesignProblem, settings: dict, out_dir: Path, load_judge=None, progress: bool = True,
               log=print) -> dict:
    """Tune the design ``problem`` (:class:`~.design.DesignProblem`, checked) with
    ``settings`` (``method``, ``budget``, ``seed``, ``batch``, ``judge_episodes``,
    ``judge_seed``, ``judge_batch``, ``judge_level``; the rest recorded as given), judge
    it at the level ``load_judge(overrides)`` gives (None: not judged) and write the folder
    (module docstring). Returns the tuning's JSON dict."""
    t0 = time.perf_counter()
    with tqdm(total=int(settings["budget"]), desc=f"design ({settings['method']})", unit="team step",
              disable=not progress) as bar:
        result = tune_design(problem, settings["method"], settings["budget"], batch=settings["batch"],
                             seed=settings["seed"], progress=bar.update)
    nominal = float(problem.evaluate(np.zeros((1, problem.size)))[0])
    best = problem.values_dict(result.best_u)
    out = {"config": settings.get("config"), "settings": settings, "objective": "miss rate (1 - success)",
           "machine": {"cpu": cpu_model(), "cores": usable_cores()}, "team": problem.base.team.policy,
           "fields": problem.names, "nominal_fields": problem.values_dict(np.zeros(problem.size)),
           "bounds": {f.key: [f.low, f.high] for f in problem.fields},
           "box": {"lower": problem.lower.tolist(), "upper": problem.upper.tolist()},
           "steps_per_evaluation": problem.steps_per_evaluation, "team_steps": result.team_steps,
           "candidates_evaluated": problem.evaluated, "nominal_value": nominal, "best_value": result.best_value,
           "best_u": result.best_u.tolist(), "tuned_fields": best,
           "set": design_overrides(problem.base, best), "history": result.history,
           "tune_wall_s": time.perf_counter() - t0}
    judged = None
    if load_judge is not None and settings["judge_episodes"] > 0:
        judged = judge_design(problem, result.best_u, load_judge, settings["judge_episodes"],
                              settings["judge_batch"], settings["judge_seed"], progress=progress)
        judged.update(level=settings["judge_level"], tuned_fields=best)
    out["wall_s"] = time.perf_counter() - t0
    with staged_output(out_dir) as folder:
        (folder / "tune.json").write_text(json.dumps(out, indent=2))
        (folder / "history.csv").write_text(history_csv(result.history))
        plot_best(result.history, nominal, folder / "tune_best.png", f"design, {settings['method']}: "
                  f"{settings.get('config')}", ylabel="miss rate on the fixed episodes", nominal_label="configured design")
        if judged is not None:
            (folder / "judged.json").write_text(json.dumps(judged, indent=2))
    log(design_summary(out, judged, out_dir))
    return out


def design_summary(out: dict, judged: dict | None, out_dir) -> str:
    """What a design tuning found, in a few lines."""
    fields = ", ".join(f"{k} {out['nominal_fields'][k]:.4g} -> {v:.4g}" for k, v in out["tuned_fields"].items())
    lines = [f"{out['settings']['method']}: best miss rate {out['best_value']:.3f} (configured design "
             f"{out['nominal_value']:.3f}) after {out['team_steps']} team steps, {out['candidates_evaluated']} "
             f"designs, in {out['wall_s']:.0f} s", f"design: {fields}",
             "as --set: " + " ".join(f'"{s}"' for s in out["set"])]
    if judged is not None:
        lines.append(_judged_line(judged))
    lines.append(f"wrote {out_dir}/tune.json, history.csv, tune_best.png" + (", judged.json" if judged else ""))
    return "\n".join(lines)


def _judged_line(judged: dict) -> str:
    s, d = judged["success"], judged["difference"]
    return (f"judged on {judged['episodes']} {judged['level']} episodes: tuned {s['tuned']['rate']:.1%}, "
            f"configured {s['configured']['rate']:.1%}, paired difference {100 * d['estimate']:+.1f} points "
            f"(95 % {100 * d['interval95'][0]:+.1f} to {100 * d['interval95'][1]:+.1f})")


def history_csv(history) -> str:
    """The history as CSV (:data:`HISTORY_COLUMNS`)."""
    return csv_text(history, HISTORY_COLUMNS)


def plot_best(history, nominal: float, path: Path, title: str,
              ylabel: str = "objective J [m] (mean over the training episodes)",
              nominal_label: str = "configured team") -> None:
    """The best value so far (and each step's value) against the team steps spent, with
    the configured team's (design's) value as a line."""
    steps = [r["team_steps"] for r in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, [r["value"] for r in history], ".", color="0.6", label="step's value")
    ax.step(steps, [r["best"] for r in history], where="post", color="C0", label="best so far")
    ax.axhline(nominal, color="C3", ls="--", lw=1, label=nominal_label)
    ax.set_xlabel("simulated team steps")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def summary(out: dict, judged: dict | None, out_dir) -> str:
    """What the run found, in a few lines."""
    lines = [f"{out['settings']['method']}: best J {out['best_value_m']:.4g} m (configured team "
             f"{out['nominal_value_m']:.4g} m) after {out['team_steps']} team steps in {out['wall_s']:.0f} s",
             f"team: {json.dumps(out['team_block'])}"]
    if judged is not None:
        lines.append(_judged_line(judged))
    lines.append(f"wrote {out_dir}/tune.json, history.csv, tune_best.png" + (", judged.json" if judged else ""))
    return "\n".join(lines)
