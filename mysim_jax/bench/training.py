"""Training throughput: what one MAPPO iteration costs against the environment alone.

Three AOT-compiled calls on the same ``num_envs`` environments, timed round-robin
(:func:`mysim_jax.bench.timing.time_round_robin`):

* ``iteration`` — :meth:`Trainer.iteration`: the rollout (policy + environment, ``num_steps``
  team steps) and the update (GAE, every epoch and minibatch);
* ``rollout`` — the rollout alone (policy sampling, critic values, environment steps);
* ``env`` — ``num_steps`` batched environment steps with zero actions (hover in velocity
  mode), no networks: the environment's own throughput in the same layout (the episode
  runner, :func:`mysim_jax.tasks.runner.rollout`, under
  :func:`mysim_jax.core.batching.vmap` in the trainer's blocks).

:func:`section_g` (BENCHMARKS.md (g)) times them on the default training file and lists the
training runs kept in ``docs/train/`` (:func:`training_runs_lines`); ``scripts/bench.py
--runs-only`` refreshes that list alone (:func:`refresh_training_runs`).
"""

from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from mysim_jax.bench.report import ROOT, TRAIN_CAPTURE, TRAIN_RUNS
from mysim_jax.bench.timing import aot_compile, contention_note, median, time_round_robin, wait_for_quiet
from mysim_jax.config.scene import dump_config, load_config
from mysim_jax.core import batching
from mysim_jax.core.config_base import ConfigError
from mysim_jax.io.training_plots import plot_runs
from mysim_jax.mappo.run import load_run_config, make_environment
from mysim_jax.mappo.run_files import THEN_DIR, read_metrics
from mysim_jax.mappo.trainer import Trainer
from mysim_jax.tasks.runner import rollout, shared_key
from mysim_jax.tasks.sweep import paired_difference_interval


@dataclass
class TrainingThroughput:
    num_envs: int
    num_steps: int
    times: dict[str, list[float]]      # call -> seconds per call (counted rounds)
    compile_s: dict[str, float]

    def steps_per_s(self, key: str) -> float:
        return self.num_envs * self.num_steps / median(self.times[key])


def measure(trainer, key, repeats: int = 3, section: str = "g") -> TrainingThroughput:
    """Time the three calls of the module docstring for ``trainer`` (a
    :class:`~mysim_jax.mappo.trainer.Trainer`)."""
    c = trainer.config
    env, env_params = trainer.env, trainer.env_params
    ts = trainer.init(key)

    one = jax.eval_shape(lambda k: env.reset(k, env_params)[1], jax.random.PRNGKey(0))
    block = batching.chunk_for(one)

    def hold(k, obs, state, params):
        return jnp.zeros(env.action_shape, jnp.float32)

    def env_only(k, obs, state):
        (_, state, _), _ = rollout(env, env_params, hold, obs, state, jax.random.split(k, c.num_steps),
                                   keys=shared_key)
        return state

    keys = jax.random.split(jax.random.PRNGKey(1), c.num_envs)
    compiled, compile_s = {}, {}
    compiled["iteration"], compile_s["iteration"], _ = aot_compile(jax.jit(trainer._iteration), ts)
    compiled["rollout"], compile_s["rollout"], _ = aot_compile(jax.jit(trainer._rollout), ts)
    compiled["env"], compile_s["env"], _ = aot_compile(jax.jit(batching.vmap(env_only, chunk=block)), keys,
                                                     ts.obs, ts.env_state)
    calls = {"iteration": lambda: compiled["iteration"](ts), "rollout": lambda: compiled["rollout"](ts),
             "env": lambda: compiled["env"](keys, ts.obs, ts.env_state)}
    times = time_round_robin(calls, repeats, section=section)
    return TrainingThroughput(c.num_envs, c.num_steps, times, compile_s)


def section_g(cfg, results) -> list[str]:
    """MAPPO: one training iteration against the rollout alone and the environment alone
    (:func:`measure`), on the environment and sizes of the default training file."""
    overrides = ["algo.num_envs=16", "algo.num_steps=4", "algo.num_minibatches=4"] if cfg.quick else []
    prepared = load_run_config(str(TRAIN_CAPTURE), overrides)
    env, env_params = make_environment(prepared)
    algo = prepared.config.algo
    trainer = Trainer(algo, env, env_params)
    wait_for_quiet(cfg.max_wait_s, "g")
    m = measure(trainer, jax.random.PRNGKey(0), repeats=2 if cfg.quick else 3)
    rate = {k: m.steps_per_s(k) for k in m.times}
    results["g"] = rate
    update_s = median(m.times["iteration"]) - median(m.times["rollout"])
    lines = [
        "## (g) Training throughput (MAPPO)",
        "",
        f"`{TRAIN_CAPTURE.relative_to(ROOT)}`" + (f" with `{' '.join(overrides)}`" if overrides else "")
        + f": {algo.num_envs} environments × {algo.num_steps} team steps per iteration, update of "
        f"{algo.update_epochs} epochs × {algo.num_minibatches} minibatches, networks {list(algo.hidden)} "
        f"(mysim_jax/bench/training.py). Each call AOT-compiled; timed round-robin, median of "
        f"{len(m.times['iteration'])} rounds. Team steps/s = policy steps of the whole team over all environments "
        f"per second, at {1.0 / env.policy_dt:g} Hz on the level `{env.level}`: a team step is {env.control_steps} "
        f"control periods of {env.scene.substeps} physics sub-steps (docs/machines.md).",
        "",
        "| call | what | s per call | team steps/s | compile [s] |",
        "|---|---|---:|---:|---:|",
        f"| iteration | rollout + GAE + update (`Trainer.iteration`) | {median(m.times['iteration']):.2f} | "
        f"{rate['iteration']:,.0f} | {m.compile_s['iteration']:.1f} |",
        f"| rollout | policy + critic + environment steps, no update | {median(m.times['rollout']):.2f} | "
        f"{rate['rollout']:,.0f} | {m.compile_s['rollout']:.1f} |",
        f"| env | environment steps alone (zero actions) | {median(m.times['env']):.2f} | {rate['env']:,.0f} | "
        f"{m.compile_s['env']:.1f} |",
        "",
        f"Training runs at **{rate['iteration'] / rate['env']:.0%}** of the environment's own steps/s; the update "
        f"takes {update_s:.2f} s of an iteration ({update_s / median(m.times['iteration']):.0%}). "
        + (f"The networks add {median(m.times['rollout']) - median(m.times['env']):.2f} s to the rollout."
           if median(m.times["rollout"]) >= median(m.times["env"]) else
           f"The rollout (policy, critic and environment) took {median(m.times['env']) - median(m.times['rollout']):.2f} s "
           "less than the environment alone with zero actions: the networks cost less than the difference the "
           "actions make to the environment's own cost (contact and line work depend on where the team flies)."),
        "",
        contention_note("g", 2 if cfg.quick else 3),
        "",
    ]
    return lines + training_runs_lines()


def _scripted_outcomes(runs) -> dict:
    """The scripted team's outcomes on the evaluation episodes of ``runs`` that compared
    against it (``eval/comparison_episodes.csv``), keyed by ``(scene, evaluation seed)``:
    episode i of a seed is the same episode in every evaluation of that environment, so a
    run evaluated on fewer episodes pairs with the first of these."""
    found = {}
    for run in runs:
        table = run / "eval" / "comparison_episodes.csv"
        base = json.loads((run / "summary.json").read_text()).get("baseline")
        if base is None or not table.is_file():
            continue
        with table.open() as f:
            rows = list(csv.DictReader(f))
        found[(_run_scene(run), base["seed"])] = np.array([r["outcome_scripted"] == "success" for r in rows])
    return found


def _run_scene(run):
    """What a kept run's evaluation flew (``scene_eval.yaml``, else the ``scene.yaml`` it
    trained on): the SHA-256 of the scene as today's schema reads it (fields added since
    the run took their defaults), without its ``levels`` block and description, which do
    not change the level it was resolved at. Two runs pair episode by episode only when
    these agree (two scenes of one name may differ: the allocation, the estimation
    errors); None for a scene today's schema refuses."""
    scene = next((run / f for f in ("scene_eval.yaml", "scene.yaml") if (run / f).is_file()), None)
    if scene is None:
        return None
    try:
        data = yaml.safe_load(dump_config(load_config(scene)))
    except ConfigError:              # a scene today's schema refuses pairs with nothing
        return None
    data.pop("levels", None)
    data.pop("description", None)
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def _run_name(run: Path) -> str:
    """A kept run's name: its folder's, or ``<run>/then`` for a chain's second run."""
    return f"{run.parent.name}/{run.name}" if run.name == THEN_DIR else run.name


def _kept_runs(folder: Path) -> list[Path]:
    """The run folders kept in ``folder`` and the second runs of kept chains
    (``<run>/then/``), sorted by name."""
    found = [p for pattern in ("*", f"*/{THEN_DIR}") for p in folder.glob(pattern)]
    return sorted((p for p in found if (p / "metrics.csv").is_file() and (p / "train.yaml").is_file()),
                  key=_run_name)


def _run_settings(run):
    """``(train.yaml as a dict, seed, init, eval seed)`` of a kept run folder."""
    cfg = yaml.safe_load((run / "train.yaml").read_text())
    run_cfg, algo = cfg.get("run", {}), cfg.get("algo", {})
    return cfg, run_cfg.get("seed", 0), algo.get("init", "none"), run_cfg.get("eval_seed")


def training_runs_lines(folder: Path = TRAIN_RUNS) -> list[str]:
    """The training runs kept in docs/train/<run>/ (copied from scripts/train.py run folders:
    summary.json, train.yaml, metrics.csv, curves.png, eval/; a chain's second run in
    <run>/then/): one table row each with the
    paired difference to the scripted team on the same episodes where it was measured, the
    spread over seeds of runs that differ only in ``run.seed``, every run's curves side
    by side (``docs/train/runs.png``) and each run's own. ``folder``: the runs' folder (default
    docs/train/; the figure is written there, the links name docs/train/ either way)."""
    runs = _kept_runs(folder)
    if not runs:
        return []
    scripted = _scripted_outcomes([run for run in runs if (run / "summary.json").is_file()])
    lines = [
        "### Training runs",
        "",
        "Each run is `python scripts/train.py configs/<file>.yaml` (with the `--set` overrides its `train.yaml` "
        "records) on the machine its row names (the run's `summary.json`, or `docs/train/machines.yaml` for runs "
        "that predate that record; docs/machines.md), its folder's `summary.json`, `train.yaml`, `metrics.csv`, `curves.png` and "
        "`eval/` kept in `docs/train/<run>/`. Training success is the share of episodes ended in the iteration "
        "that succeeded (exploration noise on); the selection curve is the deterministic policy on the fixed "
        "selection episodes; evaluation is the saved (selected) policy on `run.eval_episodes` fresh episodes "
        "(`eval_seed`), as `scripts/evaluate.py` reports it. *vs scripted* is the paired difference to the "
        "scripted team on the same evaluation episodes (the run's own `eval/comparison.json`, or the scripted "
        "outcomes another run measured on the same episodes: the same evaluation seed and the same scene, "
        "levels and description aside), with its 95 % interval. A chain's second run (`run.then`) is listed "
        "as `<run>/then`.",
        "",
        "| run | init | seed | team steps | machine | training [min] | team steps/s (update incl.) | "
        "evaluation [min] | success (95 % interval) | vs scripted [points] | how the others ended |",
        "|---|---|---:|---:|---|---:|---:|---:|---|---|---|",
    ]
    groups: dict[str, list[tuple[str, float]]] = {}
    for run in runs:
        lines.append(_run_row(run, scripted, groups))
    lines.append("")
    lines += _seed_lines(groups)
    figure = plot_runs({_run_name(run): read_metrics(run) for run in runs}, folder / "runs.png",
                       "kept training runs, side by side")
    if figure is not None:
        lines += ["![kept training runs side by side](docs/train/runs.png)", ""]
    for run in runs:
        if (run / "curves.png").is_file():
            lines += [f"![{_run_name(run)}](docs/train/{_run_name(run)}/curves.png)", ""]
    notes = [run / "NOTE.md" for run in runs if (run / "NOTE.md").is_file()]
    for note in notes:
        lines += [f"**{_run_name(note.parent)}**: " + note.read_text().strip(), ""]
    return lines


def _run_row(run: Path, scripted: dict, groups: dict) -> str:
    """One kept run's table row (``scripted``: :func:`_scripted_outcomes`); an evaluated run
    adds ``(name, success rate, seed)`` to ``groups`` under its settings without ``run.seed``."""
    cfg, seed, init, eval_seed = _run_settings(run)
    if not (run / "summary.json").is_file():
        return _unevaluated_row(run, seed, init)
    s = json.loads((run / "summary.json").read_text())
    ev = s.get("evaluation", {})
    fails = ", ".join(f"{v['count']} {k}" for k, v in ev.get("failures", {}).items() if v["count"])
    if ev.get("timeout", {}).get("count"):
        fails = (fails + ", " if fails else "") + f"{ev['timeout']['count']} timeouts"
    succ = ev.get("success")
    succ_text = (f"**{succ['rate']:.1%}** ({succ['interval95'][0]:.1%}–{succ['interval95'][1]:.1%}) of "
                 f"{ev['episodes']}" if succ else f"not evaluated (trained with --no-eval); {_selection_text(run)}")
    versus = _versus(run, s, succ, scripted, eval_seed)
    stopped = " (stopped by the time guard)" if s.get("stopped_by_time_limit") else ""
    rate = s.get("env_steps_per_s_with_update")
    rate_text = "—" if rate is None else f"{rate:,.0f}"
    eval_wall = s.get("evaluation_wall_s")
    eval_text = "—" if eval_wall is None else f"{eval_wall / 60:.1f}"       # a run trained with --no-eval
    line = (f"| `{_run_name(run)}` | {init} | {seed} | {s['env_steps']:,}{stopped} | {run_machine(run, s)} | "
            f"{s['training_wall_s_total'] / 60:.1f} | {rate_text} | "
            f"{eval_text} | {succ_text} | {versus} | {fails or '—'} |")
    if succ:
        groups.setdefault(_settings_key(cfg), []).append((_run_name(run), succ["rate"], seed))
    return line


def _settings_key(cfg: dict) -> str:
    """A kept run's settings without what differs between seeds of one training file and
    changes neither the trained team nor its evaluation: ``run.seed``, whether the scripted
    team is evaluated beside it (``run.eval_baseline``; its outcomes on the same episodes
    come from another run) and the file's ``profiles`` (other runs' overrides). An unset
    (null) setting counts as absent, as in the train.yaml of a run that predates the field."""
    cfg = {k: v for k, v in cfg.items() if k != "profiles"}
    cfg["run"] = {k: v for k, v in cfg.get("run", {}).items() if k not in ("seed", "eval_baseline")}
    return json.dumps(_without_nulls(cfg), sort_keys=True)


def _without_nulls(tree):
    """``tree`` (nested dicts) without its null entries."""
    if isinstance(tree, dict):
        return {k: _without_nulls(v) for k, v in tree.items() if v is not None}
    return tree


def run_machine(run: Path, summary: dict | None = None) -> str:
    """The machine a kept run ran on: its ``summary.json``'s ``machine``, else its entry in
    ``docs/train/machines.yaml`` (runs that predate the record), else "not recorded"."""
    if summary and summary.get("machine"):
        return summary["machine"]
    table = run.parent / "machines.yaml"
    known = yaml.safe_load(table.read_text()) if table.is_file() else {}
    return (known or {}).get(_run_name(run), "not recorded")


def _unevaluated_row(run: Path, seed, init) -> str:
    """The row of a run stopped before its evaluation: what its metrics.csv says."""
    rows = read_metrics(run)
    last = rows[-1]
    return (f"| `{_run_name(run)}` | {init} | {seed} | {int(last['env_steps']):,} | {run_machine(run)} | "
            f"{float(last['wall_s']) / 60:.1f} | — | — | not evaluated (stopped after training); "
            f"{_selection_text(run, rows)} | — | — |")


def _selection_text(run: Path, rows=None) -> str:
    """``selection success 33% at 0, ...`` from a run's metrics.csv."""
    rows = read_metrics(run) if rows is None else rows
    selected = [r for r in rows if r.get("select_success") not in ("", None)]
    sel = ", ".join(f"{float(r['select_success']):.0%} at {r['iteration']}" for r in selected)
    return f"selection success {sel or '—'}"


def _versus(run: Path, s: dict, succ, scripted: dict, eval_seed) -> str:
    """The paired difference to the scripted team: the run's own (``summary.json``), else from
    the scripted outcomes another run measured on the same episodes, else "—"."""
    versus = "—"
    if "baseline" in s:
        d = s["baseline"]["difference"]
        versus = f"{100 * d['estimate']:+.1f} ({100 * d['interval95'][0]:+.1f} to {100 * d['interval95'][1]:+.1f})"
    elif succ and (run / "eval" / "episodes.csv").is_file():
        with (run / "eval" / "episodes.csv").open() as f:
            mine = np.array([r["success"] == "1" for r in csv.DictReader(f)])
        base = scripted.get((_run_scene(run), eval_seed))
        if base is not None and len(base) >= len(mine):
            d, lo, hi = paired_difference_interval(mine, base[:len(mine)])
            versus = f"{100 * d:+.1f} ({100 * lo:+.1f} to {100 * hi:+.1f})"
    return versus


def _seed_lines(groups: dict) -> list[str]:
    """The spread over seeds of every group of more than one evaluated run. A group where a
    seed repeats is left out: the same settings and seed trained by other code (a level or a
    default changed between the runs) are not seeds of one experiment."""
    lines = []
    for members in groups.values():
        seeds = [seed for *_, seed in members]
        if len(members) > 1 and len(set(seeds)) == len(seeds):
            rates = np.array([r for _, r, _ in members])
            lines.append(f"**Over seeds** ({', '.join(f'`{n}`' for n, *_ in members)}: the same file and settings, "
                         "`run.seed` alone differs among the settings that shape the team and its evaluation): "
                         f"evaluation success mean **{rates.mean():.1%}**, "
                         f"range {rates.min():.1%}–{rates.max():.1%}, standard deviation {rates.std(ddof=1):.1%} "
                         f"over {len(rates)} seeds.")
            lines.append("")
    return lines


def refresh_training_runs(path: Path) -> int:
    """Replace the training-runs list of section (g) in ``path`` (from ``### Training runs``
    to the section's timing line) with :func:`training_runs_lines`, and say so under the
    section's heading. Measures nothing: the runs are what ``docs/train/`` holds."""
    lines = path.read_text().splitlines()
    try:
        head = lines.index("## (g) Training throughput (MAPPO)")
        start = lines.index("### Training runs", head)
    except ValueError:
        print(f"{path}: no section (g) with a training-runs list to refresh", file=sys.stderr)
        return 2
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("*(section g")
                or (i > start and lines[i].startswith("## "))), len(lines))
    when = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    note = (f"*The training-runs list below was refreshed from `docs/train/` on {when} "
            "(`scripts/bench.py --runs-only`); the throughput table is from the run named before it.*")
    body = lines[head + 1:start]
    body = [ln for ln in body if not ln.startswith("*The training-runs list below was refreshed")]
    new = lines[:head + 1] + ["", note] + [ln for ln in body if ln or True] + training_runs_lines() + lines[end:]
    # collapse the blank lines the splice may double
    out = [ln for i, ln in enumerate(new) if ln or i == 0 or new[i - 1]]
    path.write_text("\n".join(out).rstrip() + "\n")
    print(f"refreshed the training runs of section (g) in {path}")
    return 0
