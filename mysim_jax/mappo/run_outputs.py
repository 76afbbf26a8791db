"""What a training run writes once training ends, for each of its seeds: ``summary.json``,
the saved policy, the final evaluation (against the scripted team on the same episodes),
and for a run of several seeds the table of them (``seeds.json``, ``seeds.md``) and their
curves side by side. The run itself is :mod:`mysim_jax.mappo.run`."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core.machine import machine
from mysim_jax.io.training_plots import plot_curves, plot_runs
from mysim_jax.mappo.checkpoint import save_policy
from mysim_jax.mappo.networks import deterministic_policy, deterministic_policy_fn
from mysim_jax.mappo.run_files import EVAL_SCENE_FILE, SCENE_FILE, SELECT_SCENE_FILE, write_rows
from mysim_jax.tasks.contract import environment_contract
from mysim_jax.tasks.evaluate import Checkpoint, Evaluator, arrays_digest, source_digest
from mysim_jax.tasks.report import comparison_line, summary_line, write_comparison, write_evaluation


@dataclass
class SeedRun:
    """One seed of a run: its seed, its folder (the run folder itself for a run of one
    seed, ``OUT/seed_<seed>`` for several) and, once trained, its state and rows."""

    seed: int
    out: Path
    rows: list = field(default_factory=list)
    state: object = None           # this seed's TrainerState (no seed axis)


@dataclass
class Trained:
    """The training loop's result (:func:`mysim_jax.mappo.run.train_run`)."""

    seeds: list                    # SeedRun per seed, states filled in
    iteration: int
    iteration_times: list          # seconds per iteration of each chunk after the first (which compiles)
    stopped_early: bool


def summary(s, one: SeedRun, run: Trained, train_wall: float) -> dict:
    """``summary.json`` of seed ``one`` before the final evaluation (``s`` the run's session)."""
    c, rows, iteration = s.c, one.rows, run.iteration
    n_agents, _ = s.env.action_shape
    # None (JSON null) when no chunk after the first ran in this process (it compiles)
    per_iteration = float(np.median(run.iteration_times)) if run.iteration_times else None
    out = {
        "name": c.name, "config": s.p.source, "seed": one.seed, "iterations": iteration,
        "planned_iterations": c.algo.num_iterations,
        # what ended training: the step budget (algo.total_env_steps), or the optional time
        # guard (run.time_limit_min), which makes the result depend on the machine's speed
        "stopped_by": "time_limit" if run.stopped_early else "step_budget",
        "stopped_by_time_limit": run.stopped_early, "env_steps": iteration * c.algo.batch_size,
        "planned_env_steps": c.algo.num_iterations * c.algo.batch_size,
        "agent_steps": iteration * c.algo.batch_size * n_agents,
        "training_wall_s_this_process": round(train_wall, 1),
        "training_wall_s_total": float(rows[-1]["wall_s"]) if rows else 0.0,
        "median_iteration_s": per_iteration,
        # with several seeds an iteration steps every seed's environments
        "seeds_in_program": len(run.seeds),
        "env_steps_per_s_with_update": (len(run.seeds) * c.algo.batch_size / per_iteration
                                        if per_iteration else None),
        "final_train_success_rate": float(rows[-1]["success_rate"]) if rows and "success_rate" in rows[-1] else None,
        "init": c.algo.init,
        "init_policy": c.algo.init_policy,
        "machine": machine(),              # what the wall times above were measured on
        "devices": 1 if s.trainer.mesh is None else s.trainer.mesh.size,
        "processes": jax.process_count(),
    }
    bc_path = one.out / "bc.json"
    if bc_path.exists():
        out["behaviour_cloning"] = json.loads(bc_path.read_text())
    cur = s.trainer.curriculum
    if cur is not None:
        # the first iteration drawn from the full ranges (None: never reached), from the rows
        # so that a resumed run reports it too
        last = len(cur.config.stages) - 1
        full = [int(float(r["iteration"])) for r in rows
                if r.get("curriculum_stage") not in ("", None) and int(float(r["curriculum_stage"])) == last]
        out["curriculum"] = {"stages": list(cur.config.stages), "final_stage": cur.stage(one.state.curriculum),
                             "full_range_from_iteration": full[0] if full else None}
    if s.selection is not None:
        score = [float(x) for x in jax.device_get(one.state.best_score)]
        out["selection"] = {"episodes": s.selection.episodes, "seed": s.selection.seed,
                            "every": s.selection.every, "selected_iteration": int(one.state.best_iteration),
                            "successes": int(score[0]), "mean_return": score[1],
                            "scene": "training" if s.p.select_scene is None else SELECT_SCENE_FILE}
    return out


def write_seed(s, one: SeedRun, run: Trained, arrays) -> None:
    """Seed ``one``'s ``metrics.csv``, ``curves.png`` and ``policy/``."""
    c = s.c
    write_rows(one.out / "metrics.csv", one.rows)
    best = int(one.state.best_iteration)
    title = c.name if len(run.seeds) == 1 else f"{c.name}, seed {one.seed}"
    plot_curves(one.rows, one.out / "curves.png", title, best if best >= 0 else None,
                (run.iteration, c.algo.num_iterations) if run.stopped_early else None)
    n_agents, act = s.env.action_shape
    meta = {"kind": "mappo", "obs_size": int(s.env.obs_size), "action_shape": [n_agents, act],
            "hidden": list(c.algo.hidden), "activation": c.algo.activation, "normalize_obs": c.algo.normalize_obs,
            "residual": c.algo.residual,
            "env": "builtin:" + c.env.builtin if c.env.builtin else SCENE_FILE, "iteration": run.iteration,
            "selected_iteration": best if best >= 0 else run.iteration, "train": c.name, "seed": one.seed}
    if s.p.scene is not None:
        # what the policy's observations and actions mean: evaluating it elsewhere is checked against it
        meta["environment"] = environment_contract(s.env, s.env_params)
    save_policy(one.out / "policy", arrays, meta)


EVAL_RESUME = ".eval.resume"
"""The folder (in the run folder) where the final evaluation saves its progress."""


class FinalEvaluation:
    """The final evaluation of a capture run's policies on the same fresh episodes of the
    evaluation scene: one compiled program flies either a policy or the scripted team (an
    argument says which), and the scripted team flies once for every seed. Each evaluation
    saves its progress every 5 minutes in ``OUT/.eval.resume/``
    (:class:`~mysim_jax.tasks.evaluate.Checkpoint`; fingerprinted by the evaluation scene,
    the policy's arrays and the package's source), so a run resumed after it was stopped in
    its evaluation goes on from there; the caller removes the folder when the run's files
    are written."""

    def __init__(self, s):
        self.s = s
        c, eval_env = s.c, s.eval_env
        # on the evaluation scene (env.eval_level): the policy's residual base, if any, is
        # that scene's scripted team
        self.base = eval_env.scripted_actions if c.algo.residual else None
        net = deterministic_policy_fn(s.trainer.actor, c.algo.normalize_obs, self.base)

        def either(key, obs, state, params, args):
            arrays, scripted = args
            return jnp.where(scripted, eval_env.scripted_actions(state, params), net(key, obs, state, params, arrays))

        self.evaluator = Evaluator(eval_env, s.eval_params, either, batch=c.run.eval_batch,
                                   env_batching=s.trainer.env_batching)
        self.key = jax.random.PRNGKey(c.run.eval_seed)
        self._scripted = None
        scene = s.p.eval_scene if s.p.evaluates_elsewhere else s.p.scene
        self._scene = f"{scene.name}, level {scene.level}"

    def _checkpoint(self, name: str, what: str) -> Checkpoint:
        fingerprint = json.dumps({"scene": self._scene, "team": what,
                                  "code": source_digest()})
        return Checkpoint(self.s.p.out / EVAL_RESUME / f"{name}.npz", fingerprint)

    def __call__(self, one: SeedRun, arrays, summary: dict) -> dict:
        """Evaluate seed ``one``'s policy ``arrays``: ``one.out/eval/`` and the summary's
        evaluation entries; returns the evaluation's metrics."""
        s, c, p = self.s, self.s.c, self.s.p
        desc = "evaluation" if len(s.seeds) == 1 else f"evaluation, seed {one.seed}"
        stats = self.evaluator(self.key, c.run.eval_episodes, (arrays, jnp.bool_(False)), progress=s.progress,
                               desc=desc, checkpoint=self._checkpoint(f"seed_{one.seed}", arrays_digest(arrays)))
        eval_scene = p.eval_scene if p.evaluates_elsewhere else p.scene
        eval_file = EVAL_SCENE_FILE if p.evaluates_elsewhere else SCENE_FILE
        policy = deterministic_policy(s.trainer.actor, arrays, c.algo.normalize_obs, self.base)
        metrics = write_evaluation(one.out / "eval", eval_scene, s.eval_env, s.eval_params, policy,
                                   policy_name=str(one.out / "policy"), episodes=c.run.eval_episodes,
                                   batch=c.run.eval_batch, seed=c.run.eval_seed, config_path=str(p.out / eval_file),
                                   progress=s.progress, animate=False, stats=stats)
        what = (f"trained (MAPPO), evaluated at level {eval_scene.level}" if p.evaluates_elsewhere
                else "trained (MAPPO)")
        if len(s.seeds) > 1:
            what += f", seed {one.seed}"
        s.log(summary_line(p.scene.name, what, metrics, one.out / "eval"))
        summary["evaluation"] = {k: metrics[k] for k in ("episodes", "success", "failures", "timeout",
                                                         "mean_return", "mean_length_steps", "wall_s")}
        summary["evaluation"]["level"] = eval_scene.level
        summary["evaluation"]["scene"] = eval_file
        summary["training_level"] = p.scene.level
        if c.run.eval_baseline:
            if self._scripted is None:
                self._scripted = self.evaluator(self.key, c.run.eval_episodes, (arrays, jnp.bool_(True)),
                                                progress=s.progress, desc="scripted team",
                                                checkpoint=self._checkpoint("scripted", "scripted"))
            comparison = write_comparison(one.out / "eval", stats, self._scripted, names=("trained", "scripted"),
                                          seed=c.run.eval_seed)
            s.log(comparison_line(comparison))
            summary["baseline"] = comparison
        return metrics


def _spread(values: list[float]) -> dict:
    v = np.asarray(values, float)
    return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max())}


def write_seeds_table(out: Path, name: str, summaries: list[dict], seed_runs: list[SeedRun]) -> dict:
    """``seeds.json`` and ``seeds.md`` in ``out``: each seed's evaluation success (with its
    interval and, with a baseline, the paired difference to the scripted team), selected
    iteration and final training success, and the mean, standard deviation and range over
    seeds; ``curves.png`` with every seed's curves. Returns the table's dict."""
    per_seed = []
    for one, sm in zip(seed_runs, summaries):
        row = {"seed": one.seed, "folder": one.out.name,
               "selected_iteration": sm.get("selection", {}).get("selected_iteration"),
               "final_train_success_rate": sm.get("final_train_success_rate")}
        if "evaluation" in sm:
            row["success_rate"] = sm["evaluation"]["success"]["rate"]
            row["interval95"] = sm["evaluation"]["success"].get("interval95")
        if "baseline" in sm:
            d = sm["baseline"]["difference"]
            row["vs_scripted_points"] = 100 * d["estimate"]
            row["vs_scripted_interval95"] = [100 * x for x in d["interval95"]]
        per_seed.append(row)
    table = {"name": name, "seeds": [r["seed"] for r in per_seed], "per_seed": per_seed}
    for key in ("success_rate", "vs_scripted_points", "final_train_success_rate"):
        values = [r[key] for r in per_seed if r.get(key) is not None and math.isfinite(r[key])]
        if len(values) == len(per_seed):
            table[key] = _spread(values)
    (out / "seeds.json").write_text(json.dumps(table, indent=2))
    lines = [f"# {name}: {len(per_seed)} seeds trained in one program", "",
             "| seed | evaluation success (95 %) | vs scripted, points (95 %) | selected iteration |"
             " final training success |", "|---:|---:|---:|---:|---:|"]

    def pct(x):
        return "" if x is None else f"{100 * x:.1f} %"

    for r in per_seed:
        ci = f" ({pct(r['interval95'][0])}-{pct(r['interval95'][1])})" if r.get("interval95") else ""
        vs = (f"{r['vs_scripted_points']:+.1f} ({r['vs_scripted_interval95'][0]:+.1f} to "
              f"{r['vs_scripted_interval95'][1]:+.1f})" if "vs_scripted_points" in r else "")
        selected = "last" if r["selected_iteration"] is None else r["selected_iteration"]
        lines.append(f"| {r['seed']} | {pct(r.get('success_rate'))}{ci} | {vs} | {selected} | "
                     f"{pct(r['final_train_success_rate'])} |")
    lines.append("")
    for key, label, scale, unit in (("success_rate", "evaluation success", 100, " %"),
                                    ("vs_scripted_points", "vs scripted", 1, " points"),
                                    ("final_train_success_rate", "final training success", 100, " %")):
        if key in table:
            t = table[key]
            lines.append(f"- {label}: mean {scale * t['mean']:.1f}{unit}, sd {scale * t['sd']:.1f}, "
                         f"range {scale * t['min']:.1f} to {scale * t['max']:.1f}")
    (out / "seeds.md").write_text("\n".join(lines) + "\n")
    plot_runs({f"seed {one.seed}": one.rows for one in seed_runs}, out / "curves.png",
              f"{name}: {len(seed_runs)} seeds")
    return table
